"""What a rollout worker reads of the simulated state, in torch where the state lives (MuJoCo Warp's device).

The NumPy originals (`workers.body.features`, `workers.rewards`) stay what MuJoCo C's workers compute, bit
for bit; these give the same numbers to float32 rounding (tests compare them), on any device, so that a
worker beside a GPU simulator copies to the host what its trajectory stores, not the state to compute it
from. A `DeviceState` is a simulator's state on its device (`Simulator.device_state`,
`StepResult.on_device`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
import torch

from workers.body.character import Character
from workers.models.body_state import (
    ANG,
    LIN,
    POS,
    QUAT,
    from_heading,
    heading_cos_sin,
    pack,
    quat_mul,
    quat_to_matrix,
    to_heading,
)
from workers.motion.library import MotionLibrary
from workers.rewards import DEFAULT_WEIGHTS, IMITATION_TERMS, check_weights


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


class DeviceReference:
    """A motion library's stored frames on a device, looked up there: the reference states and features a
    worker beside a GPU simulator compares its characters with (`MotionLibrary.state` and `.features`)."""

    def __init__(self, library: MotionLibrary, device: torch.device | str):
        self.library, self.device = library, torch.device(device)
        kin, feats = library.stored_frames()

        def table(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a, np.float32), device=self.device)

        self.qpos, self.qvel, self.body_states, self.features = map(table, (kin.qpos, kin.qvel, pack(kin), feats))
        self._pd_targets = table(library.stored_pd_targets())

    def rows(self, clip_ids: np.ndarray, frames: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
        rows, cycles = self.library.rows(np.asarray(clip_ids, int), np.asarray(frames, int))
        return torch.as_tensor(rows, device=self.device), cycles

    def state(self, clip_ids: np.ndarray, frames: np.ndarray) -> DeviceState:
        """The reference states at the given frames (looping clips turned and moved by their cycles, as
        `MotionLibrary.state` does)."""
        rows, cycles = self.rows(clip_ids, frames)
        qpos, qvel, bs = self.qpos[rows], self.qvel[rows], self.body_states[rows]
        if not np.any(cycles):
            return DeviceState(qpos, qvel, bs)
        yaw, shift = self.library.cycle_power(np.asarray(clip_ids, int), cycles)
        yaw = torch.as_tensor(yaw, dtype=torch.float32, device=self.device)
        shift = torch.as_tensor(shift, dtype=torch.float32, device=self.device)
        c, s = torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]  # broadcast against [N, k]
        zero = torch.zeros_like(yaw)
        qz = torch.stack((torch.cos(0.5 * yaw), zero, zero, torch.sin(0.5 * yaw)), dim=-1)  # [N, 4]
        root = torch.cat((from_heading(qpos[:, None, :3], c, s)[:, 0] + shift, quat_mul(qz, qpos[:, 3:7])), dim=-1)
        qpos = torch.cat((root, qpos[:, 7:]), dim=-1)
        qvel = torch.cat((from_heading(qvel[:, None, :3], c, s)[:, 0], qvel[:, 3:]), dim=-1)
        vectors = from_heading(
            torch.stack((bs[..., POS], bs[..., LIN], bs[..., ANG]), dim=-2), c[..., None], s[..., None]
        )
        bs = torch.cat(
            (
                vectors[..., 0, :] + shift[:, None],
                quat_mul(qz[:, None], bs[..., QUAT]),
                vectors[..., 1, :],
                vectors[..., 2, :],
            ),
            dim=-1,
        )
        return DeviceState(qpos, qvel, bs)

    def frame_features(self, clip_ids: np.ndarray, frames: np.ndarray) -> torch.Tensor:
        """s [N, D] of the reference at the given frames (`MotionLibrary.features`; s is unchanged by cycles)."""
        return self.features[self.rows(clip_ids, frames)[0]]

    def pd_targets(self, clip_ids: np.ndarray, frames: np.ndarray) -> torch.Tensor:
        """[N, A] PD targets holding the reference's joints at the given frames (`MotionLibrary.pd_targets`; a
        cycle turns and moves the root only, so the joints' targets are the stored frame's)."""
        return self._pd_targets[self.rows(clip_ids, frames)[0]]


def tracking_reward(state: torch.Tensor, ref_state: torch.Tensor, weights: torch.Tensor, temperature: float):
    """ControlVAE's Eq. 20, exp(−‖W(s̃ − s)‖₁ / T_V) [...] (`workers.replay.balancing.tracking_reward`)."""
    return torch.exp(-((ref_state - state) * weights).abs().sum(-1) / temperature)


def _quat_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return 2.0 * torch.arccos(torch.clamp((a * b).sum(-1).abs(), 0.0, 1.0))


def imitation_errors(character: Character, sim: DeviceState, ref: DeviceState) -> dict[str, torch.Tensor]:
    """The squared errors e_k [N] of each imitation term (`workers.rewards.imitation_errors`)."""
    device = sim.qpos.device
    balls = torch.as_tensor(character.ball_qpos, device=device)
    hinges = torch.as_tensor(character.hinge_qpos, device=device)
    ee = torch.as_tensor(character.end_effectors, device=device)
    pose = _quat_angle(sim.qpos[:, 3:7], ref.qpos[:, 3:7]) ** 2
    pose = pose + (_quat_angle(sim.qpos[:, balls], ref.qpos[:, balls]) ** 2).sum(-1)
    pose = pose + ((sim.qpos[:, hinges] - ref.qpos[:, hinges]) ** 2).sum(-1)
    dof0 = character.root_dofs
    velocity = ((sim.qvel[:, dof0:] - ref.qvel[:, dof0:]) ** 2).sum(-1)

    def ee_local(bs: torch.Tensor) -> torch.Tensor:
        c, s = heading_cos_sin(bs[:, 0, QUAT])
        return to_heading(bs[:, ee, POS] - bs[:, :1, POS], c[..., 0], s[..., 0])

    end_effector = ((ee_local(sim.body_states) - ee_local(ref.body_states)) ** 2).sum((-1, -2))
    root = ((sim.body_states[:, 0, POS] - ref.body_states[:, 0, POS]) ** 2).sum(-1)
    return {"pose": pose, "velocity": velocity, "end_effector": end_effector, "root": root}


def imitation_reward(
    character: Character, sim: DeviceState, ref: DeviceState, weights: Mapping[str, float] = DEFAULT_WEIGHTS
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """(r [N], {term: exp(−w_k e_k) [N]}) of `workers.rewards.imitation_reward`, where the states are."""
    check_weights(weights)
    errors = imitation_errors(character, sim, ref)
    terms = {k: torch.exp(-float(weights.get(k, 0.0)) * errors[k]) for k in IMITATION_TERMS}
    return torch.stack(list(terms.values())).prod(0), terms
