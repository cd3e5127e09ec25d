"""PULSE's goal s_g-mimic (§4.1) against the reference-frame goal s̃_{t+1}: known answers and drift."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.body.features import StateLayout
from workers.evaluation.imitation import reference_actor
from workers.models import body_state
from workers.models.tracking_goal import goal, goal_dim, mimic_goal
from workers.rewards import imitation_observation
from workers.sim.env import BatchedSim, without_tracking_termination

B = 15


def parts(g: torch.Tensor) -> dict[str, torch.Tensor]:
    """s_g-mimic [N, 24·B] split into its six per-body parts [N, B, k]."""
    g = g.reshape(g.shape[0], B, 24)
    names, sizes = ("dpos", "drot", "dlin", "dang", "rot", "pos"), (3, 6, 3, 3, 6, 3)
    return dict(zip(names, g.split(sizes, dim=-1), strict=True))


def yaw_about_z(bs: torch.Tensor, angle: float, shift: torch.Tensor) -> torch.Tensor:
    """Body states rotated by `angle` about the world's vertical axis, then moved by `shift` [3]."""
    c, s = np.cos(angle), np.sin(angle)
    r = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
    q = torch.tensor([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)], dtype=torch.float32).expand(bs.shape[:-1] + (4,))
    out = bs.clone()
    out[..., 0:3] = bs[..., 0:3] @ r.T + shift
    out[..., 3:7] = body_state.quat_mul(q, bs[..., 3:7])
    out[..., 7:10] = bs[..., 7:10] @ r.T
    out[..., 10:13] = bs[..., 10:13] @ r.T
    return out


@pytest.fixture(scope="module")
def states(walk_run):
    """Reference body states of walk and run at a few frames [6, B, 13], and the same one frame later."""
    clips, frames = np.array([0, 0, 0, 1, 1, 1]), np.array([0, 7, 20, 3, 11, 15])
    now = torch.from_numpy(body_state.pack(walk_run.state(clips, frames)))
    nxt = torch.from_numpy(body_state.pack(walk_run.state(clips, frames + 1)))
    return now, nxt


def test_sizes():
    assert goal_dim("mimic", B) == 24 * B == 360
    assert goal_dim("reference", B) == StateLayout(B).dim
    with pytest.raises(ValueError, match="unknown goal"):
        goal_dim("future", B)


def test_on_the_reference_the_offsets_vanish_and_the_rest_is_the_references_own_features(states):
    """Character = reference: p̂ − p, v̂ − v, ω̂ − ω are 0, θ̂ ⊖ θ is the identity, and θ̂ and p̂ − p_root are
    the rotations and root-relative positions of s̃ (the reference's heading is the character's)."""
    ref, _ = states
    p = parts(mimic_goal(ref, ref))
    for k in ("dpos", "dlin", "dang"):
        assert p[k].abs().max() < 1e-6
    identity_6d = torch.tensor([1.0, 0, 0, 0, 1, 0])
    torch.testing.assert_close(p["drot"], identity_6d.expand_as(p["drot"]), atol=1e-5, rtol=0)
    s = body_state.features(ref)
    lay = StateLayout(B)
    torch.testing.assert_close(p["pos"].reshape(6, -1), s[:, lay.pos], atol=1e-5, rtol=0)
    torch.testing.assert_close(p["rot"].reshape(6, -1), s[:, lay.rot], atol=1e-5, rtol=0)


def test_a_character_displaced_from_its_reference_sees_the_displacement_in_its_own_heading_frame(states):
    """A character that is the reference moved by d and turned by ψ about the vertical: the reference-frame
    goal is the same as on the reference; s_g-mimic's p̂ − p is −d as the turned character sees it (every
    body), and θ̂ ⊖ θ is a turn by −ψ about the vertical."""
    _, ref = states
    d, psi = torch.tensor([0.7, -0.4, 0.0]), 0.5
    char = yaw_about_z(ref, psi, torch.zeros(3))
    char[..., 0:3] += d  # turned about the world origin, then moved: every body is now off by its own offset
    torch.testing.assert_close(goal("reference", char, ref), goal("reference", ref, ref))
    p = parts(mimic_goal(char, ref))
    heading = body_state.yaw(char[:, 0, 3:7])  # [N]
    h_inv = body_state.yaw_matrix(-heading)  # world -> the character's heading frame
    want = ((ref[..., 0:3] - char[..., 0:3]).unsqueeze(-2) @ h_inv.transpose(-1, -2).unsqueeze(1)).squeeze(-2)
    torch.testing.assert_close(p["dpos"], want, atol=1e-5, rtol=0)
    turn = body_state.yaw_matrix(torch.tensor(-psi))
    want_rot = torch.cat((turn[:, 0], turn[:, 1])).expand_as(p["drot"])
    torch.testing.assert_close(p["drot"], want_rot, atol=1e-5, rtol=0)


def test_turning_and_moving_the_whole_scene_changes_nothing(states):
    """Character and reference turned and moved together: the goal is in the character's heading frame."""
    now, nxt = states
    shift = torch.tensor([3.0, -2.0, 0.0])
    before = mimic_goal(now, nxt)
    after = mimic_goal(yaw_about_z(now, 1.1, shift), yaw_about_z(nxt, 1.1, shift))
    torch.testing.assert_close(after, before, atol=2e-5, rtol=0)


def test_drift_on_a_long_rollout_is_invisible_to_the_reference_goal_and_measured_by_mimic(character, walk_run):
    """PD tracking of walk, open loop, for 3 s (2.4 loops of the 1.27 s clip): the character drifts from
    the reference. The tracker's "imitation" observation (s, s̃_{t+1}) is the same for the drifted
    character and for that character moved back over the reference's root, so nothing in it tells the
    policy where the reference is; s_g-mimic's root offset is the measured drift, to float32."""
    config = without_tracking_termination()
    sim = BatchedSim(character, walk_run, 1, config, seed=0)
    sim.reset(np.zeros(1, int), np.zeros(1, int), np.zeros(1, int))
    act = reference_actor(walk_run)
    drift = []
    for _ in range(int(3 * config.control_hz)):
        bs = body_state.pack(sim.kin_state())
        ref = sim.reference_next_body_states()
        g = parts(mimic_goal(torch.from_numpy(bs), torch.from_numpy(ref)))
        measured = np.linalg.norm(ref[0, 0, :2] - bs[0, 0, :2])
        np.testing.assert_allclose(np.linalg.norm(g["dpos"][0, 0, :2].numpy()), measured, rtol=1e-4, atol=1e-6)
        drift.append(measured)
        sim.step(act(sim, bs))
    assert max(drift) > 0.25  # far enough for PULSE's 0.5 m success radius to care
    # Move the drifted character back horizontally over the reference's root: the imitation observation
    # does not change (s is heading-frame and root-relative), s_g-mimic does.
    back = bs.copy()
    back[..., :2] += ref[0, 0, :2] - bs[0, 0, :2]
    s_next = sim.reference_next_features()
    obs_drifted = imitation_observation(body_state.features_np(bs), s_next)
    obs_back = imitation_observation(body_state.features_np(back), s_next)
    np.testing.assert_allclose(obs_drifted, obs_back, atol=1e-5)
    g_back = mimic_goal(torch.from_numpy(back), torch.from_numpy(ref))
    g_drifted = mimic_goal(torch.from_numpy(bs), torch.from_numpy(ref))
    assert (g_back - g_drifted).abs().max() > 0.2
