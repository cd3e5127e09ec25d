"""The replay buffer as a component: the workers' trajectories, batches for the learners, data balancing's returns."""

from __future__ import annotations

from typing import Any

import numpy as np

from orchestrator.components.base import incarnation
from orchestrator.schema import Config
from orchestrator.world import load_character_and_library, seed_of
from workers.motion.library import MotionLibrary
from workers.replay.balancing import frame_sums, library_rows
from workers.replay.buffer import ReplayBuffer
from workers.types import StartBatch, Trajectory, WindowBatch


class ReplayActor(ReplayBuffer):
    def __init__(self, cfg: Config, num_bodies: int, action_dim: int):
        super().__init__(cfg.algo.loop.replay_capacity, num_bodies, action_dim, seed=seed_of(cfg, 1))
        self.incarnation = incarnation()
        self.cfg = cfg
        self.library: MotionLibrary | None = None  # loaded when data balancing first asks

    def add_trajectory(self, trajectory: Trajectory) -> dict[str, Any]:
        """Store a trajectory; a summary for the loop (the trajectory itself stays here)."""
        self.add(trajectory)
        extras = trajectory.extras
        counts = ("switches", "switch_falls", "switch_recoveries")
        return {
            "transitions": int(trajectory.actions.shape[0] * trajectory.actions.shape[1]),
            "version": int(trajectory.version),
            "episode_ends": int(trajectory.done.sum()),
            "size": len(self),
            "incarnation": self.incarnation,
            "reward_sum": float(extras["reward"].sum()) if "reward" in extras else 0.0,
            **{k: int(extras[k]) for k in counts if k in extras},
        }

    def frame_returns(self, values: np.ndarray, gamma: float) -> tuple[np.ndarray, np.ndarray]:
        """Data balancing (ControlVAE Eq. 18): (visits, summed V*) per library frame over the stored
        trajectories, bootstrapped with `values` [library frames]."""
        if self.library is None:
            _, self.library = load_character_and_library(self.cfg)
        lib = self.library
        clip, frame, returns = self.discounted_returns(gamma, lambda c, f: values[library_rows(lib, c, f)])
        return frame_sums(library_rows(lib, clip, frame), returns, lib.total_frames)

    def sample_batches(self, count: int, size: int, length: int) -> list[WindowBatch]:
        """`count` batches of windows; none from an empty buffer, which is one that Ray has just
        restarted (the loop reloads it from the last checkpoint when it reports its new life)."""
        if len(self) == 0:
            return []
        return [self.sample_windows(size, length) for _ in range(count)]

    def sample_start_batches(self, count: int, size: int, length: int) -> list[StartBatch]:
        """`count` batches of `size` single stored states (ControlVAE's VAE starts), each with
        `size · (length + 1)` more for the state normaliser: as many as windows of `length` feed it."""
        if len(self) == 0:
            return []
        return [self.sample_starts(size, size * (length + 1)) for _ in range(count)]
