"""Plain data shared by the simulator, the motion library, the rollout workers, the replay and the learners.

- `KinState`: the kinematic state of a batch of characters (simulated or reference).
- `Trajectory`: one coarse collect of a rollout worker, as the replay buffer stores it.
- `WindowBatch`, `StartBatch`: what the replay buffer hands the learners.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class KinState:
    """Kinematic state of a batch of characters. Shapes: N characters, B bodies.

    Everything is in world coordinates (z-up). Both the simulator and the
    motion library produce it, so reference and simulated states share one
    definition; `workers.body.features` turns it into s and Φ(s).
    """

    qpos: np.ndarray  # [N, nq] generalised coordinates
    qvel: np.ndarray  # [N, nv] generalised velocities (root angular velocity in the root frame)
    xpos: np.ndarray  # [N, B, 3] body origins
    xquat: np.ndarray  # [N, B, 4] body rotations (w, x, y, z)
    lin_vel: np.ndarray  # [N, B, 3] body-origin linear velocities
    ang_vel: np.ndarray  # [N, B, 3] body angular velocities

    def __getitem__(self, idx) -> KinState:
        return KinState(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))

    def __len__(self) -> int:
        return self.qpos.shape[0]


@dataclass
class Trajectory:
    """One coarse collect of one rollout worker: T control steps of M environments.

    Float arrays are float32.
    """

    states: np.ndarray  # [T, M, B, 13] body state before each step
    next_states: np.ndarray  # [T, M, B, 13] its true successor (taken before any reset)
    actions: np.ndarray  # [T, M, A] the PD targets applied (noise included)
    done: np.ndarray  # [T, M] bool: the environment was reset after this step
    clip_id: np.ndarray  # [T, M] reference clip of each state
    frame: np.ndarray  # [T, M] reference frame of each state
    version: int  # the policy version that collected it
    worker: int  # the worker that collected it
    # What the method's learners need beyond the body states (`workers.rollout`, `workers.recorders`):
    # the policy's observations, log-probabilities and values, Φ(s), rewards, truncations. The buffer keeps
    # `reward` [T, M] (data balancing reads it) and cuts links at `switched` [T, M]; it ignores the rest.
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def num_transitions(self) -> int:
        return int(self.done.size)


@dataclass
class WindowBatch:
    """n windows of L consecutive transitions."""

    states: np.ndarray  # [n, L+1, B, 13] the L states and the true successor of the last
    actions: np.ndarray  # [n, L, A]
    clip_id: np.ndarray  # [n] reference clip of the first state
    frame: np.ndarray  # [n] reference frame of the first state
    version: np.ndarray  # [n] policy version that collected the first transition


@dataclass
class StartBatch:
    """n single stored states, the starts of synthetic rollouts, and more states for input statistics."""

    states: np.ndarray  # [n, B, 13]
    clip_id: np.ndarray  # [n] reference clip of each state
    frame: np.ndarray  # [n] reference frame of each state
    norm_states: np.ndarray  # [k, B, 13] drawn independently of the starts
