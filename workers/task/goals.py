"""Goals of the downstream tasks in rollouts and evaluation: drawing them, and judging each episode's success.

`GoalSampler` holds one goal per environment in the format `workers.losses.task` takes
([M, G], world frame) and redraws it at random times; `SuccessTracker` turns a run of
steps into one success per episode. Both are NumPy. One control step, in this order:

    g = sampler.goals.copy()                          # the goals in force during the step
    result = sim.step(policy(obs, g))
    bs = result.body_states                           # [N, B, 13] body states
    changed = sampler.advance(sim, bs)                # the next step's goals
    tracker.update(bs, g, result.fell, changed)
    ended = np.flatnonzero(result.done)
    success = tracker.result(ended); tracker.reset(ended)
    sim.reset(ended); sampler.reset(sim, sim.body_states(), ended)

A goal is redrawn with probability change_rate / control_hz after each step, so goals last
1 / change_rate seconds on average (ControlVAE changes them every 72 control steps: 3.6 s at
its 20 Hz, 2.4 s or 0.42/s at our 30 Hz). Ranges (`DEFAULT_RANGES`, overridden by name through `ranges`):

  heading     θ* ∈ [−π, π] (world), v* ∈ [0, 3] m/s              ControlVAE §4.3
  steering    θ_h*, θ_v* ∈ [−π, π] (world), v* ∈ [0, 3] m/s      ControlVAE §4.3
  height      H ∈ {−1, +1}, equally likely                        ControlVAE §4.3
  point_goal  a target on the ground 1–5 m from the root, at a uniform bearing
  vr          the head and hands of the environment's reference clip (`workers.models.body_state.VR_POINTS`)
              one frame ahead: the positions to reach by the end of the coming step, which is where
              the step's loss and success are measured. These goals follow the clip and never "change".
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import torch

from workers.losses.task import GOAL_DIMS, task_terms
from workers.models.body_state import VR_TERMS, pack, vr_points

if TYPE_CHECKING:
    from workers.sim.env import Simulator

DEFAULT_RANGES: dict[str, tuple[float, float]] = {
    "heading": (-math.pi, math.pi),  # θ* of heading, θ_h* of steering (radians, world frame)
    "direction": (-math.pi, math.pi),  # θ_v* of steering (radians, world frame)
    "speed": (0.0, 3.0),  # v* of heading and steering (m/s)
    "distance": (1.0, 5.0),  # point goal: horizontal distance from the root (m); the bearing is uniform
    "height": (-1.0, 1.0),  # the two values H takes, each with probability 1/2
}

# Success criteria (`SuccessTracker`). A goal held for a while is judged on its last WINDOW_S
# seconds, and only if it was in force for SETTLE_S + WINDOW_S seconds: a goal drawn just before
# the next change or the episode's end says nothing about the policy. Whether a goal is judged never
# depends on how it went, so skipping short goals does not bias the success rate.
SUCCESS_RADIUS_M = 0.5  # vr: PULSE's tracking threshold; point_goal: how close the root must come
WINDOW_S = 1.0  # heading, steering, height: judged on this last stretch of each goal (window means)
SETTLE_S = 1.0  # ... after at least this long to respond (turn around, get up to speed, stand up)
HEADING_TOL_RAD = 0.35  # mean facing / travel-direction error (20°)
SPEED_TOL = 0.3  # mean |v* − v| / max(v*, 1): the loss's normalised speed error
STEERING_MIN_SPEED = 0.5  # m/s: below this v* the travel direction of a near-still root is noise, not judged
HEIGHT_HIGH_M = 0.8  # H = +1: mean root height above this (standing: 0.85–0.87 m in the walk clip)
HEIGHT_LOW_M = 0.4  # H = −1: mean root height below this (a full squat keeps it near 0.45 m)
POINT_GOAL_MIN_S = 6.0  # a point goal is judged if in force this long: 5 m at 1 m/s after a 1 s turn


def _check_ranges(ranges: Mapping[str, tuple[float, float]] | None) -> dict[str, tuple[float, float]]:
    merged = dict(DEFAULT_RANGES)
    for name, (lo, hi) in (ranges or {}).items():
        if name not in DEFAULT_RANGES:
            raise ValueError(f"unknown goal range {name!r}; expected one of {sorted(DEFAULT_RANGES)}")
        if not lo <= hi:
            raise ValueError(f"goal range {name!r} must have low <= high, got ({lo}, {hi})")
        merged[name] = (float(lo), float(hi))
    return merged


def vr_targets(sim: Simulator, ids: np.ndarray | None = None) -> np.ndarray:
    """[n, 9] the tracked points (head, left hand, right hand) of the reference of environments `ids`
    (all by default) one frame ahead: what `sim.reference_state()` holds after the next step."""
    ids = np.arange(sim.num_envs) if ids is None else np.asarray(ids, dtype=int)
    ref = sim.library.state(sim.clip_id[ids], sim.start_frame[ids] + sim.steps[ids] + 1)
    return vr_points(torch.from_numpy(pack(ref))).reshape(len(ids), 9).numpy()


class GoalSampler:
    """One goal per environment, drawn at episode starts and redrawn at random times."""

    def __init__(
        self,
        task: str,
        num_envs: int,
        control_hz: float,
        change_rate: float,
        rng: np.random.Generator,
        ranges: Mapping[str, tuple[float, float]] | None = None,
    ):
        if task not in GOAL_DIMS:
            raise ValueError(f"unknown task {task!r}; expected one of {sorted(GOAL_DIMS)}")
        if not 0 <= change_rate <= control_hz:
            raise ValueError(f"change_rate must be in [0, control_hz = {control_hz}] per second, got {change_rate}")
        self.task, self.num_envs, self.rng = task, num_envs, rng
        self.change_prob = change_rate / control_hz  # per control step
        self.ranges = _check_ranges(ranges)
        self.goals = np.zeros((num_envs, GOAL_DIMS[task]), np.float32)  # [M, G] world frame

    def reset(self, sim: Simulator | None, bs: np.ndarray | torch.Tensor, ids: np.ndarray) -> None:
        """New goals for environments `ids` that start episodes; bs [M, B, 13] are the body states of
        all environments (after `sim.reset(ids)`; NumPy, or a tensor on a device, of which a point goal
        copies the roots it is drawn around), sim the `Simulator` (read for `vr` only)."""
        ids = np.asarray(ids, dtype=int)
        if len(ids) == 0:
            return
        self.goals[ids] = vr_targets(sim, ids) if self.task == "vr" else self._draw(bs, ids)

    def advance(self, sim: Simulator | None, bs: np.ndarray | torch.Tensor) -> np.ndarray:
        """After a control step: redraw each goal with probability change_rate / control_hz (vr: follow
        the reference instead); returns [M] bool, which goals changed (vr: none)."""
        if self.task == "vr":
            self.goals[:] = vr_targets(sim)
            return np.zeros(self.num_envs, bool)
        changed = self.rng.random(self.num_envs) < self.change_prob
        ids = np.flatnonzero(changed)
        if len(ids):
            self.goals[ids] = self._draw(bs, ids)
        return changed

    def _draw(self, bs: np.ndarray | torch.Tensor, ids: np.ndarray) -> np.ndarray:
        """Fresh goals [n, G] for environments `ids`."""
        n, r, uniform = len(ids), self.ranges, self.rng.uniform
        if self.task == "heading":
            return np.stack((uniform(*r["heading"], n), uniform(*r["speed"], n)), axis=-1)
        if self.task == "steering":
            return np.stack((uniform(*r["heading"], n), uniform(*r["direction"], n), uniform(*r["speed"], n)), -1)
        if self.task == "height":
            return self.rng.choice(np.asarray(r["height"]), size=(n, 1))
        if not isinstance(bs, torch.Tensor):  # point_goal
            bs = np.asarray(bs)
        if bs.shape[0] != self.num_envs:
            raise ValueError(f"bs must hold all {self.num_envs} environments, got {bs.shape[0]}")
        root = bs[ids, 0, :2]
        root = root.cpu().numpy() if isinstance(root, torch.Tensor) else root  # of a device's: these rows copied
        distance, bearing = uniform(*r["distance"], n), uniform(-math.pi, math.pi, n)
        return root + distance[:, None] * np.stack((np.cos(bearing), np.sin(bearing)), axis=-1)

    def state_dict(self) -> dict:
        return {"task": self.task, "goals": self.goals.copy(), "rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        if state["task"] != self.task or state["goals"].shape != self.goals.shape:
            raise ValueError(f"goal state of {state['task']!r} {state['goals'].shape} does not fit {self.task!r}")
        self.goals[:] = state["goals"]
        self.rng.bit_generator.state = state["rng"]


class SuccessTracker:
    """Whether each episode met its goals (constants above):

      vr          PULSE's rule: at every step the tracked points' mean distance to their targets is at most
                  SUCCESS_RADIUS_M (with all_points, every point's distance: stricter); and no fall, a
                  clause of ours (PULSE's has none; `fall_fails=False` leaves it out, and a fallen body is
                  then judged by its points' distances alone, as it lies)
      point_goal  every judged goal (in force POINT_GOAL_MIN_S) brought the root within SUCCESS_RADIUS_M
                  of the target horizontally at some step, and no fall
      heading     every judged goal, over its last WINDOW_S: mean heading error < HEADING_TOL_RAD and mean
                  |v* − v| < SPEED_TOL · max(v*, 1) (v along θ*, as in the loss); and no fall
      steering    as heading for the facing error and the planar speed, and (for v* ≥ STEERING_MIN_SPEED)
                  the direction of the window's mean planar velocity within HEADING_TOL_RAD of θ_v*:
                  the root sways sideways within each stride, its mean velocity does not; and no fall
      height      every judged goal: mean root height over its last WINDOW_S above HEIGHT_HIGH_M (H = +1)
                  or below HEIGHT_LOW_M (H = −1). Falls do not count: H = −1 asks the character to lie
                  down (ControlVAE), and getting up takes the hand and knee contacts the simulator calls falls.

    `result` gives 1.0 (success), 0.0 (failure) or NaN where nothing was judged (every goal too short
    and no fall); average with np.nanmean.
    """

    def __init__(self, task: str, num_envs: int, control_hz: float, all_points: bool = False, fall_fails: bool = True):
        if task not in GOAL_DIMS:
            raise ValueError(f"unknown task {task!r}; expected one of {sorted(GOAL_DIMS)}")
        self.task, self.num_envs, self.all_points = task, num_envs, all_points
        self.fall_fails = fall_fails and task != "height"  # height: lying down is what H = −1 asks
        self.window = max(1, round(WINDOW_S * control_hz))
        min_s = POINT_GOAL_MIN_S if task == "point_goal" else SETTLE_S + WINDOW_S
        self.min_steps = max(1, round(min_s * control_hz))
        metrics = {"heading": 2, "steering": 4, "height": 1}.get(task, 0)
        self._metrics = np.zeros((num_envs, self.window, metrics))  # per-step quantities, a ring per env
        self._goal = np.zeros((num_envs, GOAL_DIMS[task]))  # the goal in force
        self._steps = np.zeros(num_envs, int)  # steps of the goal in force
        self._reached = np.zeros(num_envs, bool)  # point_goal: the goal in force was reached
        self._failed = np.zeros(num_envs, bool)
        self._judged = np.zeros(num_envs, bool)

    def update(self, bs: np.ndarray, goals: np.ndarray, fell: np.ndarray, changed: np.ndarray | None = None) -> None:
        """One control step of all environments: body states bs [M, B, 13] after it, the goals [M, G] in
        force during it, whether they fell [M] and whether their goal changes after it [M] (`advance`)."""
        bs_t, goals_t = (torch.as_tensor(np.asarray(a), dtype=torch.float64) for a in (bs, goals))
        terms = {k: v.numpy() for k, v in task_terms(self.task, bs_t, goals_t).items()}
        if self.fall_fails:
            fell = np.asarray(fell, bool)
            self._failed |= fell
            self._judged |= fell
        rows = np.arange(self.num_envs)
        if self.task == "vr":
            d = np.stack([terms[k] for k in VR_TERMS], axis=-1)
            self._failed |= (d.max(-1) if self.all_points else d.mean(-1)) > SUCCESS_RADIUS_M
            self._judged[:] = True
        elif self.task == "point_goal":
            self._reached |= terms["distance"] <= SUCCESS_RADIUS_M
        elif self.task == "height":
            self._metrics[rows, self._steps % self.window] = np.asarray(bs)[:, 0, 2:3]
        else:
            m = [terms["heading"], terms["speed"]]
            if self.task == "steering":
                m += [np.asarray(bs)[:, 0, 7], np.asarray(bs)[:, 0, 8]]  # root planar velocity
            self._metrics[rows, self._steps % self.window] = np.stack(m, axis=-1)
        self._goal[:] = goals
        self._steps += 1
        ids = np.flatnonzero(np.zeros(self.num_envs, bool) if changed is None else changed)
        if len(ids):
            ok, judged = self._judge(ids)
            self._failed[ids] |= judged & ~ok
            self._judged[ids] |= judged
            self._steps[ids] = 0
            self._reached[ids] = False

    def _judge(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(met [n], judged [n]) of the goals in force in environments `ids`; vr judges every step instead."""
        if self.task == "vr":
            return np.ones(len(ids), bool), np.zeros(len(ids), bool)
        judged = self._steps[ids] >= self.min_steps
        if self.task == "point_goal":
            return self._reached[ids], judged
        mean = self._metrics[ids].mean(axis=1)  # a judged goal has a full window
        goal = self._goal[ids]
        if self.task == "height":
            return np.where(goal[:, 0] > 0, mean[:, 0] > HEIGHT_HIGH_M, mean[:, 0] < HEIGHT_LOW_M), judged
        ok = (mean[:, 0] < HEADING_TOL_RAD) & (mean[:, 1] < SPEED_TOL)
        if self.task == "steering":
            d = goal[:, 1] - np.arctan2(mean[:, 3], mean[:, 2])  # θ_v* − direction of the mean velocity
            ok &= (goal[:, 2] < STEERING_MIN_SPEED) | (np.abs(np.arctan2(np.sin(d), np.cos(d))) < HEADING_TOL_RAD)
        return ok, judged

    def result(self, ids: np.ndarray) -> np.ndarray:
        """[n] success of the episodes of environments `ids` so far, their goals in force included:
        1.0, 0.0, or NaN where nothing could be judged."""
        ids = np.asarray(ids, dtype=int)
        ok, judged = self._judge(ids)
        failed = self._failed[ids] | (judged & ~ok)
        return np.where(failed, 0.0, np.where(self._judged[ids] | judged, 1.0, np.nan))

    def reset(self, ids: np.ndarray) -> None:
        """Start new episodes in environments `ids`."""
        ids = np.asarray(ids, dtype=int)
        for a in (self._metrics, self._goal, self._steps, self._reached, self._failed, self._judged):
            a[ids] = 0

    def state_dict(self) -> dict:
        names = ("_metrics", "_goal", "_steps", "_reached", "_failed", "_judged")
        return {n: getattr(self, n).copy() for n in names}

    def load_state_dict(self, state: dict) -> None:
        for n, v in state.items():
            getattr(self, n)[:] = v
