"""The one episode runner: a simulator's environments stepped together under an actor, for up to a number of
control steps, with a hook after each step that may end the run.

    steps = run_episodes(sim, act, 600, after)    # act(sim, bs) -> actions [N, A]; after(t, result) -> True to stop

`act` gets the simulator and its environments' body states [N, B, 13] before the step (the step result's, after
the first), as `Policy.act` and the evaluation actors take them; `after` gets the step's number t (1 for the
first) and its `StepResult`, and records what the caller measures. Nothing is reset: the evaluations let a fallen
character keep trying, or end its episode by their own rule. Every evaluation protocol (`workers.evaluation`) and
the recordings its videos render run their episodes here.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from workers.sim.base import Simulator, StepResult

Actor = Callable[[Simulator, np.ndarray], np.ndarray]
AfterStep = Callable[[int, StepResult], bool | None]


def run_episodes(sim: Simulator, act: Actor, steps: int, after: AfterStep | None = None, states: bool = True) -> int:
    """Step `sim` under `act` for up to `steps` control steps, calling `after(t, result)` after each (t from 1);
    stop early when it returns True. Returns the number of steps taken. With `states=False`, `act` gets None for
    the body states and reads what it needs from the simulator (they are then never packed for it)."""
    bs = sim.body_states() if states else None
    for t in range(1, steps + 1):
        result = sim.step(np.asarray(act(sim, bs)))
        if after is not None and after(t, result):
            return t
        bs = result.body_states if states else None
    return steps
