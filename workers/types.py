"""Plain data types shared by the simulator, the motion library and the learners."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class KinState:
    """Kinematic state of a batch of characters. Shapes: N characters, B bodies.

    Everything is in world coordinates (z-up). Both the simulator and the
    motion library produce it, so reference and simulated states share one
    definition; `workers.sim.features` turns it into s and Φ(s).
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
