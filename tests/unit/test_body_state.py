"""The torch body state agrees with the NumPy features and the simulator's kinematics."""

from __future__ import annotations

import numpy as np
import torch

from workers.body import rotations as rot
from workers.body.features import state_features
from workers.models import body_state as B


def test_features_match_numpy(walk_run):
    kin = walk_run.state(np.array([0, 1, 0, 1]), np.array([0, 7, 50, 123]))  # frames past the end loop around
    got = B.features(torch.as_tensor(B.pack(kin)).double()).numpy()
    np.testing.assert_allclose(got, state_features(kin), atol=1e-5)


def test_numpy_features_of_body_states_are_the_torch_ones(walk_run):
    bs = B.pack(walk_run.state(np.array([0, 1, 0, 1]), np.array([0, 7, 50, 123])))
    got = B.features_np(bs)
    assert got.dtype == np.float32 and got.shape == (4, 16 * bs.shape[1] + 3)
    np.testing.assert_allclose(got, B.features(torch.from_numpy(bs)).numpy(), atol=2e-6)


def test_features_of_batched_time_axes(walk_run):
    kin = walk_run.state(np.zeros(6, int), np.arange(6))
    bs = torch.as_tensor(B.pack(kin))
    flat = B.features(bs)
    np.testing.assert_allclose(B.features(bs.reshape(2, 3, *bs.shape[1:])).reshape(6, -1), flat, atol=1e-6)


def test_quat_from_rotvec_matches_numpy_and_is_smooth_at_zero():
    v = torch.tensor([[0.0, 0.0, 0.0], [1e-5, 0, 0], [0.3, -0.2, 0.9], [3.0, 0.1, 0.0]], dtype=torch.float64)
    np.testing.assert_allclose(B.quat_from_rotvec(v).numpy(), rot.from_expmap(v.numpy()), atol=1e-12)
    v0 = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(B.quat_from_rotvec(v0)[0, 1:].sum(), v0)
    np.testing.assert_allclose(g.numpy(), [[0.5, 0.5, 0.5]])  # d(v/2)/dv at zero


def test_integrate_inverts_the_velocity_delta(walk_run):
    kin0 = walk_run.state(np.array([0, 1]), np.array([3, 9]))
    kin1 = walk_run.state(np.array([0, 1]), np.array([4, 10]))
    bs0, bs1 = torch.as_tensor(B.pack(kin0)).double(), torch.as_tensor(B.pack(kin1)).double()
    out = B.integrate(bs0, B.heading_velocity_delta(bs0, bs1), 1 / 30)
    np.testing.assert_allclose(out[..., B.LIN], bs1[..., B.LIN], atol=1e-12)
    np.testing.assert_allclose(out[..., B.ANG], bs1[..., B.ANG], atol=1e-12)
    np.testing.assert_allclose(out[..., B.QUAT].norm(dim=-1), 1.0, atol=1e-12)


def test_integrate_constant_spin_about_z():
    # One body at the origin spinning at 2 rad/s about z, moving at 1 m/s along x, no change:
    # after 0.25 s it is at x = 0.25 and has turned by 0.5 rad, whatever the scheme.
    bs = torch.zeros(1, 1, 13, dtype=torch.float64)
    bs[..., 3] = 1.0
    bs[..., 7] = 1.0
    bs[..., 12] = 2.0
    for scheme in B.INTEGRATORS:
        out = B.integrate(bs, torch.zeros(1, 1, 6, dtype=torch.float64), 0.25, scheme)
        np.testing.assert_allclose(out[0, 0, :3], [0.25, 0, 0], atol=1e-12)
        np.testing.assert_allclose(B.yaw(out[0, 0, 3:7]), 0.5, atol=1e-12)


def test_heading_cos_sin_is_the_yaw_angle_and_the_rotations_are_the_yaw_matrices():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(50, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    c, s = B.heading_cos_sin(q)
    assert c.shape == s.shape == (50, 1, 1)
    theta = B.yaw(q)
    np.testing.assert_allclose(c[:, 0, 0], torch.cos(theta), atol=1e-12)
    np.testing.assert_allclose(s[:, 0, 0], torch.sin(theta), atol=1e-12)
    v = torch.randn(50, 7, 3, generator=g, dtype=torch.float64)
    by_matrix = (B.yaw_matrix(-theta)[:, None] @ v[..., None])[..., 0]
    c, s = c[:, 0], s[:, 0]  # one axis (7 vectors) before the coordinates
    np.testing.assert_allclose(B.to_heading(v, c, s), by_matrix, atol=1e-12)
    np.testing.assert_allclose(B.from_heading(B.to_heading(v, c, s), c, s), v, atol=1e-12)
    # A root whose x axis points straight up has no heading: atan2(0, 0) = 0, so cos 1 and sin 0, not NaN.
    up = torch.tensor([[np.cos(np.pi / 4), 0.0, -np.sin(np.pi / 4), 0.0]], dtype=torch.float64)
    c, s = B.heading_cos_sin(up)
    assert abs(float(c) - 1.0) < 1e-7 and abs(float(s)) < 1e-7


def test_features_turn_with_the_character_and_their_gradient_is_finite(walk_run):
    """Turning the whole scene about z leaves s unchanged (it lives in the heading frame), and the elementwise
    rotation is differentiable everywhere a body state can be."""
    bs = torch.as_tensor(B.pack(walk_run.state(np.array([0, 1, 1]), np.array([2, 30, 77])))).double()
    turn = torch.tensor([np.cos(0.35), 0.0, 0.0, np.sin(0.35)], dtype=torch.float64)  # 0.7 rad about z
    turned = bs.clone()
    for part in (B.POS, B.LIN, B.ANG):
        turned[..., part] = (B.yaw_matrix(torch.tensor(0.7, dtype=torch.float64)) @ bs[..., part, None])[..., 0]
    turned[..., B.QUAT] = B.quat_mul(turn.expand_as(bs[..., B.QUAT]), bs[..., B.QUAT])
    np.testing.assert_allclose(B.features(turned), B.features(bs), atol=1e-6)  # float32 clip data
    x = bs.clone().requires_grad_()
    (grad,) = torch.autograd.grad(B.features(x).square().sum(), x)
    assert torch.isfinite(grad).all() and grad[..., B.QUAT].abs().sum() > 0
