"""A task policy's evaluation in the simulator: return, success, style and falls over a fixed set of goals.

One episode per goal: `num_goals` environments start from library states drawn by
`seed` (reference state initialisation), each with one goal drawn by the same seed
and kept for the whole episode (success rules judge a goal held long enough: a point
goal for 6 s), and run for `seconds` under the task policy's mean (z = μ_p + μ_g, no
sampling). An episode
ends at a fall; nothing else ends it (no tracking-failure end: the reference only
supplies the start, and the goals of `vr`).

- `return`: the normalised return, the mean over episodes of Σ_t e^(−L_g(s_t)) / T with
  T the full length, so that a fall forfeits the rest of the episode; 1 is every goal
  met at every step.
- `success`: the share of episodes that meet the task's own success rule
  (`workers.task.goals.SuccessTracker`), over the episodes it could judge; for VR tracking also
  `success_pulse`, PULSE's rule as the paper states it, without our no-fall clause (a fallen body is
  judged by its tracked points' distances as it lies, until every episode has fallen).
- `style_deviation_deg`: the mean absolute deviation of the applied action from the
  frozen decoder's own action D(s, z) over the steps before a fall, in degrees (the
  helper branch's Δa; exactly 0 without it).
- `time_until_fall`: per episode, seconds until the fall (the full length if none).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch

from workers.body.character import Character
from workers.losses.task import task_loss
from workers.motion.library import MotionLibrary
from workers.sim.env import SimConfig, Simulator, StepResult, make_sim, without_tracking_termination
from workers.sim.episodes import run_episodes
from workers.task.goals import SuccessTracker
from workers.task.policy import TaskRolloutPolicy


def evaluate_task_policy(
    policy: TaskRolloutPolicy,
    character: Character,
    library: MotionLibrary,
    num_goals: int,
    seconds: float,
    sim_config: SimConfig | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Metrics and curves of the configured `policy` (skill set, weights loaded); see the module docstring."""
    config = replace(without_tracking_termination(sim_config), end_on_fall=True)
    sim = make_sim(character, library, num_goals, config, seed=seed)
    task = policy.config.task
    stochastic, policy.stochastic = policy.stochastic, False
    trained, policy.config = policy.config, replace(policy.config, change_rate=0.0)
    policy.bind(num_goals, np.random.default_rng(seed), torch.Generator().manual_seed(seed))
    success = SuccessTracker(task, num_goals, config.control_hz)
    # VR tracking: PULSE's rule as the paper has it, without our no-fall clause, beside ours.
    pulse = SuccessTracker(task, num_goals, config.control_hz, fall_fails=False) if task == "vr" else None
    steps = max(int(round(seconds * config.control_hz)), 1)
    alive = np.ones(num_goals, bool)
    fell_at = np.full(num_goals, steps)
    reward_sum, deviation_sum, lived = np.zeros(num_goals), np.zeros(num_goals), np.zeros(num_goals)
    term_sums: dict[str, float] = {}
    curve = np.full(steps, np.nan)
    roots = np.full((steps + 1, num_goals, 2), np.nan)
    goals = np.zeros((steps, num_goals, policy.goals.goals.shape[1]), np.float32)
    roots[0] = sim.body_states()[:, 0, :2]
    step: dict[str, np.ndarray] = {}  # this step's applied and decoded actions

    def act(sim: Simulator, bs: np.ndarray) -> np.ndarray:
        step["applied"], step["decoded"] = policy.actions(sim, bs)
        return step["applied"]

    def after(t: int, result: StepResult) -> bool:
        i, bs = t - 1, result.body_states
        goals[i] = policy.goals.goals  # those in force during the step (`advance` comes below)
        goal = torch.from_numpy(policy.goals.goals)
        total, terms = task_loss(task, torch.from_numpy(bs), goal, policy.config.weights, policy.config.fall_height)
        r = np.exp(-(total - policy.config.weights.get("fall", 1.0) * terms["fall"]).numpy())
        reward_sum[alive] += r[alive]
        deviation_sum[alive] += np.abs(step["applied"] - step["decoded"]).mean(-1)[alive]
        lived[alive] += 1
        curve[i] = float(r[alive].mean()) if alive.any() else np.nan
        for k, v in terms.items():
            term_sums[k] = term_sums.get(k, 0.0) + float(v.numpy()[alive].sum())
        in_force = policy.goals.goals.copy()
        changed = policy.goals.advance(sim, bs)
        success.update(bs, in_force, result.fell & alive, changed & alive)
        if pulse is not None:
            pulse.update(bs, in_force, result.fell & alive, changed & alive)
        fell = alive & result.fell
        fell_at[fell] = t
        alive[:] &= ~result.fell
        roots[t, alive] = bs[alive, 0, :2]
        return not alive.any()

    try:
        run_episodes(sim, act, steps, after)
    finally:
        policy.stochastic, policy.config = stochastic, trained
    ok = success.result(np.arange(num_goals))
    hz = config.control_hz
    extra = {}
    if pulse is not None:
        pulse_ok = pulse.result(np.arange(num_goals))
        extra["success_pulse"] = float(np.nanmean(pulse_ok)) if np.isfinite(pulse_ok).any() else float("nan")
    return {
        "return": float((reward_sum / steps).mean()),
        "success": float(np.nanmean(ok)) if np.isfinite(ok).any() else float("nan"),
        **extra,
        "style_deviation_deg": float(np.degrees(deviation_sum.sum() / max(lived.sum(), 1))),
        "time_until_fall_mean": float(fell_at.mean() / hz),
        "fell": float((fell_at < steps).mean()),
        "terms": {k: v / max(lived.sum(), 1) for k, v in term_sums.items()},
        "per_episode": {
            "success": ok.tolist(),
            "seconds": (fell_at / hz).tolist(),
            "return": (reward_sum / steps).tolist(),
        },
        "curve_t": (np.arange(steps) / hz).tolist(),
        "curve": curve.tolist(),
        "roots": roots,
        "goals": goals,
    }
