"""What a tracking policy is told about the reference's next state: its goal.

Two goals, by name:

- "reference": the reference's next state features s̃_{t+1}
  (`workers.body.features`), in the reference's own heading frame. What
  ControlVAE's posterior reads and our tracking expert observed first. It is the
  same wherever the reference is relative to the character, so a character that
  drifts from its clip in position or heading cannot see it.
- "mimic": PULSE's s_g-mimic (Luo et al. 2024, §4.1, after PHC): the reference's
  next state as differences to the character, all in the character's heading
  frame (yaw of its root), per body: the position offset p̂_{t+1} − p_t, the
  rotation offset θ̂_{t+1} ⊖ θ_t, the velocity offsets v̂_{t+1} − v_t and
  ω̂_{t+1} − ω_t, the reference's rotation θ̂_{t+1} and its position relative to
  the character's root, p̂_{t+1} − p_root. 24 numbers a body. The paper writes
  ω̂_t − ω_t; we take t + 1 like the other terms (PHC's released code does too).

Both are computed in torch from body states [..., B, 13] (`workers.models.body_state`)
so that a learner can take them from stored windows and a policy from a simulator
(`workers.sim.base.Simulator.tracking_goal`).
"""

from __future__ import annotations

import torch

from workers.body.features import StateLayout
from workers.models.body_state import ANG, LIN, POS, QUAT, features, quat_to_matrix, yaw, yaw_matrix

GOALS = ("reference", "mimic")
MIMIC_PER_BODY = 24


def check(kind: str, key: str = "goal") -> None:
    if kind not in GOALS:
        raise ValueError(f"{key}: unknown goal {kind!r}; expected one of {GOALS}")


def goal_dim(kind: str, num_bodies: int) -> int:
    check(kind)
    return StateLayout(num_bodies).dim if kind == "reference" else MIMIC_PER_BODY * num_bodies


def mimic_goal(bs: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PULSE's s_g-mimic [..., 24·B] of the character's body states bs and the reference's ref [..., B, 13]."""
    lead = bs.shape[:-2]
    h_inv = yaw_matrix(-yaw(bs[..., 0, QUAT])).unsqueeze(-3)  # [..., 1, 3, 3], world -> character heading

    def to_heading(v: torch.Tensor) -> torch.Tensor:
        return (h_inv @ v.unsqueeze(-1)).squeeze(-1)

    def six_d(m: torch.Tensor) -> torch.Tensor:
        return torch.cat((m[..., :, 0], m[..., :, 1]), dim=-1)

    rot, rot_ref = quat_to_matrix(bs[..., QUAT]), quat_to_matrix(ref[..., QUAT])
    ref_heading = h_inv @ rot_ref  # θ̂ in the character's heading frame
    offset = ref_heading @ rot.transpose(-1, -2) @ h_inv.transpose(-1, -2)  # θ̂ ⊖ θ, in that frame too
    parts = (
        to_heading(ref[..., POS] - bs[..., POS]),
        six_d(offset),
        to_heading(ref[..., LIN] - bs[..., LIN]),
        to_heading(ref[..., ANG] - bs[..., ANG]),
        six_d(ref_heading),
        to_heading(ref[..., POS] - bs[..., :1, POS]),
    )
    return torch.cat(parts, dim=-1).reshape(lead + (-1,))


def goal(kind: str, bs: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """The goal [..., G] of body states bs toward the reference's next body states ref [..., B, 13]."""
    check(kind)
    return features(ref) if kind == "reference" else mimic_goal(bs, ref)
