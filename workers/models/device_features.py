"""What a rollout worker reads of the simulated state, in torch where the state lives (MuJoCo Warp's device).

The NumPy originals (`workers.body.features`, `workers.rewards`) stay what MuJoCo C's workers compute, bit
for bit; these give the same numbers to float32 rounding (tests compare them), on any device, so that a
worker beside a GPU simulator copies to the host what its trajectory stores, not the state to compute it
from. A `DeviceState` is a simulator's state on its device (`Simulator.device_state`,
`StepResult.on_device`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from workers.body.character import Character
from workers.models.body_state import ANG, LIN, POS, QUAT, heading_cos_sin, quat_to_matrix, to_heading


class DeviceState(NamedTuple):
    """N environments' state on the simulator's device (float32)."""

    qpos: torch.Tensor  # [N, nq]
    qvel: torch.Tensor  # [N, nv]
    body_states: torch.Tensor  # [N, B, 13], `workers.models.body_state`'s layout

    def rows(self, ids) -> DeviceState:
        """The state of environments `ids` (indices on the host or the device)."""
        index = torch.as_tensor(ids, device=self.qpos.device)
        return DeviceState(self.qpos[index], self.qvel[index], self.body_states[index])


def _six_d(m: torch.Tensor) -> torch.Tensor:
    """The first two columns of rotation matrices [..., 3, 3], column by column: [..., 6] (`rotations.to_6d`)."""
    return torch.cat((m[..., :, 0], m[..., :, 1]), dim=-1)


def amp_features(character: Character, state: DeviceState) -> torch.Tensor:
    """AMP's Φ(s) [N, amp_dim] (float32) of a device state: `workers.body.features.amp_features`'s layout."""
    qpos, qvel, bs = state
    n = qpos.shape[0]
    root = bs[:, 0]
    c, s = heading_cos_sin(root[:, QUAT])  # [N, 1, 1]
    root_cols = quat_to_matrix(root[:, QUAT]).transpose(-1, -2)[:, :2]  # [N, 2, 3]: the first two columns
    root_rot = to_heading(root_cols, c[..., 0], s[..., 0]).reshape(n, 6)
    velocities = to_heading(torch.stack((root[:, LIN], root[:, ANG]), dim=1), c[..., 0], s[..., 0])  # [N, 2, 3]
    balls = torch.as_tensor(character.ball_qpos, device=qpos.device)
    joint_rot = _six_d(quat_to_matrix(qpos[:, balls]))  # [N, n_ball, 6]
    hinges = torch.as_tensor(character.hinge_qpos, device=qpos.device)
    ee = torch.as_tensor(character.end_effectors, device=qpos.device)
    ee_rel = to_heading(bs[:, ee, POS] - bs[:, :1, POS], c[..., 0], s[..., 0])  # [N, E, 3]
    return torch.cat(
        (
            root[:, POS][:, 2:3],
            root_rot,
            velocities.reshape(n, 6),
            joint_rot.reshape(n, -1),
            qpos[:, hinges],
            qvel[:, 6:],
            ee_rel.reshape(n, -1),
        ),
        dim=1,
    )
