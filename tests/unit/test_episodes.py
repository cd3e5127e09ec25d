"""workers.sim.episodes.run_episodes: the one episode runner, against the loop it replaces, on MuJoCo C."""

from __future__ import annotations

import numpy as np

from workers.sim.env import make_sim
from workers.sim.episodes import run_episodes


def _targets(sim, bs):
    """PD targets from the body states the runner hands over (a feedback law: wrong states, other actions)."""
    return np.tile(np.tanh(bs[:, :, 2].mean(-1, keepdims=True)), (1, sim.character.num_actions)) * 0.3


def test_the_runner_steps_as_the_hand_written_loop_and_hands_over_the_step_results_states(character, walk_run):
    by_hand = make_sim(character, walk_run, 3, seed=5)
    bs, want = by_hand.body_states(), []
    for _ in range(6):
        result = by_hand.step(_targets(by_hand, bs))
        want.append(result.kin.qpos.copy())
        bs = result.body_states
    sim = make_sim(character, walk_run, 3, seed=5)
    got, seen = [], []

    def after(t, result):
        seen.append(t)
        got.append(result.kin.qpos.copy())

    assert run_episodes(sim, _targets, 6, after) == 6
    assert seen == [1, 2, 3, 4, 5, 6]
    np.testing.assert_array_equal(np.stack(got), np.stack(want))


def test_the_runner_stops_when_the_hook_says_and_without_states_hands_over_none(character, walk_run):
    sim = make_sim(character, walk_run, 2, seed=0)
    given = []

    def act(sim, bs):
        given.append(bs)
        return np.zeros((2, sim.character.num_actions))

    assert run_episodes(sim, act, 50, lambda t, result: t == 4, states=False) == 4
    assert given == [None] * 4 and int(sim.steps[0]) == 4
