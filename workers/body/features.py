"""State features: ControlVAE's state s and AMP's discriminator observation Φ(s).

Both are computed from a `KinState` for all characters and bodies at once.
Everything is expressed in the heading frame: root yaw only, gravity up, so both
are unchanged when the whole character is rotated about the vertical axis or
moved horizontally.

s (ControlVAE §3.4.1), per body, in body order:
  position relative to the root [B, 3], 6D rotation [B, 6], linear velocity
  [B, 3], angular velocity [B, 3]; then every body's height [B] and the root's
  up axis [3]. With 15 bodies, 243 numbers.

Φ(s) (AMP §5.3): root height [1], root rotation [6], root linear and angular
  velocity [3 + 3]; each joint's local rotation (6D for ball joints, the angle
  for hinges) [8·6 + 4]; each joint's local velocity (the actuated qvel) [28];
  hands and feet positions relative to the root [4 · 3]. 105 numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.body import rotations as rot
from workers.body.character import Character
from workers.types import KinState


@dataclass(frozen=True)
class StateLayout:
    """Where each part of s lies in the flat vector."""

    num_bodies: int

    @property
    def pos(self) -> slice:
        return slice(0, 3 * self.num_bodies)

    @property
    def rot(self) -> slice:
        return slice(3 * self.num_bodies, 9 * self.num_bodies)

    @property
    def lin_vel(self) -> slice:
        return slice(9 * self.num_bodies, 12 * self.num_bodies)

    @property
    def ang_vel(self) -> slice:
        return slice(12 * self.num_bodies, 15 * self.num_bodies)

    @property
    def height(self) -> slice:
        return slice(15 * self.num_bodies, 16 * self.num_bodies)

    @property
    def up(self) -> slice:
        return slice(16 * self.num_bodies, 16 * self.num_bodies + 3)

    @property
    def dim(self) -> int:
        return 16 * self.num_bodies + 3


def heading_inverse(root_quat: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rotations from world to the heading frame of each root [N, 4]."""
    return rot.yaw_matrix(-rot.yaw(root_quat))


def _to_heading(h_inv: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Apply [N, 3, 3] to vectors [N, 3] or [N, B, 3]."""
    if v.ndim == 2:
        return (h_inv @ v[:, :, None])[:, :, 0]
    return v @ h_inv.transpose(0, 2, 1)


def state_features(s: KinState) -> np.ndarray:
    """ControlVAE's s, [N, 16·B + 3], float32."""
    n, b = s.xpos.shape[:2]
    h_inv = heading_inverse(s.xquat[:, 0])
    pos = _to_heading(h_inv, s.xpos - s.xpos[:, :1])
    mats = h_inv[:, None] @ rot.to_matrix(s.xquat)
    rot6 = rot.to_6d(mats)
    lin = _to_heading(h_inv, s.lin_vel)
    ang = _to_heading(h_inv, s.ang_vel)
    up = mats[:, 0, :, 2]
    out = np.concatenate(
        (pos.reshape(n, -1), rot6.reshape(n, -1), lin.reshape(n, -1), ang.reshape(n, -1), s.xpos[..., 2], up),
        axis=1,
    )
    return out.astype(np.float32)


def amp_dim(character: Character) -> int:
    n_ball = len(character.ball_qpos)
    n_hinge = len(character.hinge_qpos)
    return 1 + 6 + 3 + 3 + 6 * n_ball + n_hinge + character.num_actions + 3 * len(character.end_effectors)


def amp_features(character: Character, s: KinState) -> np.ndarray:
    """AMP's Φ(s), [N, amp_dim], float32."""
    n = s.qpos.shape[0]
    h_inv = heading_inverse(s.xquat[:, 0])
    root_mat = h_inv @ rot.to_matrix(s.xquat[:, 0])
    joint_rot = rot.to_6d(rot.to_matrix(s.qpos[:, character.ball_qpos]))  # [N, n_ball, 6]
    ee = _to_heading(h_inv, s.xpos[:, character.end_effectors] - s.xpos[:, :1])
    out = np.concatenate(
        (
            s.xpos[:, 0, 2:3],
            rot.to_6d(root_mat),
            _to_heading(h_inv, s.lin_vel[:, 0]),
            _to_heading(h_inv, s.ang_vel[:, 0]),
            joint_rot.reshape(n, -1),
            s.qpos[:, character.hinge_qpos],
            s.qvel[:, 6:],
            ee.reshape(n, -1),
        ),
        axis=1,
    )
    return out.astype(np.float32)


def relative_position_error(xpos: np.ndarray, ref_xpos: np.ndarray) -> np.ndarray:
    """Mean over non-root bodies of ‖(x_j − x_root) − (x̃_j − x̃_root)‖: [..., B, 3] × 2 -> [...].

    Body 0 is the root; its own term is always zero, so it is left out of the mean.
    """
    rel = xpos[..., 1:, :] - xpos[..., :1, :]
    ref_rel = ref_xpos[..., 1:, :] - ref_xpos[..., :1, :]
    return np.linalg.norm(rel - ref_rel, axis=-1).mean(-1)
