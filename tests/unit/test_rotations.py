import numpy as np
import pytest

from workers.body import rotations as rot


@pytest.fixture
def quats():
    rng = np.random.default_rng(0)
    return rot.normalize(rng.normal(size=(64, 4)))


def test_matrix_round_trip(quats):
    m = rot.to_matrix(quats)
    np.testing.assert_allclose(m @ m.transpose(0, 2, 1), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    back = rot.from_matrix(m)
    # q and -q are the same rotation.
    same = np.minimum(np.abs(back - quats).max(-1), np.abs(back + quats).max(-1))
    assert same.max() < 1e-10


def _from_6d(d6: np.ndarray) -> np.ndarray:
    """Rotation matrices from 6D by Gram-Schmidt: what the 6D numbers must allow."""
    c0 = d6[..., :3] / np.linalg.norm(d6[..., :3], axis=-1, keepdims=True)
    b = d6[..., 3:] - np.sum(c0 * d6[..., 3:], axis=-1, keepdims=True) * c0
    c1 = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.stack((c0, c1, np.cross(c0, c1)), axis=-1)


def test_6d_round_trips_to_the_rotation_matrix(quats):
    m = rot.to_matrix(quats)
    d6 = rot.to_6d(m)
    assert d6.shape == (64, 6)
    np.testing.assert_allclose(_from_6d(d6), m, atol=1e-12)
    # The 6D numbers are the first two columns.
    np.testing.assert_allclose(d6[:, :3], m[:, :, 0])
    np.testing.assert_allclose(d6[:, 3:], m[:, :, 1])


def test_rotate_matches_matrix(quats):
    v = np.random.default_rng(1).normal(size=(64, 3))
    np.testing.assert_allclose(rot.rotate(quats, v), (rot.to_matrix(quats) @ v[:, :, None])[:, :, 0], atol=1e-12)


def test_expmap_round_trip_and_known_value(quats):
    v = rot.to_expmap(quats)
    assert np.linalg.norm(v, axis=-1).max() <= np.pi + 1e-12
    back = rot.from_expmap(v)
    np.testing.assert_allclose(np.abs(np.sum(back * quats, -1)), 1.0, atol=1e-12)
    # 90 degrees about z: (cos 45°, 0, 0, sin 45°).
    np.testing.assert_allclose(rot.from_expmap(np.array([0, 0, np.pi / 2])), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])


def test_mul_composes_like_matrices(quats):
    a, b = quats[:32], quats[32:]
    np.testing.assert_allclose(rot.to_matrix(rot.mul(a, b)), rot.to_matrix(a) @ rot.to_matrix(b), atol=1e-12)


def test_slerp_endpoints_and_midpoint():
    a = np.array([1.0, 0, 0, 0])
    b = rot.from_expmap(np.array([0, 0, 1.0]))
    np.testing.assert_allclose(rot.slerp(a, b, 0.0), a, atol=1e-12)
    np.testing.assert_allclose(rot.slerp(a, b, 1.0), b, atol=1e-12)
    np.testing.assert_allclose(rot.to_expmap(rot.slerp(a, b, 0.5)), [0, 0, 0.5], atol=1e-12)


def test_yaw_of_a_yaw_rotation():
    theta = np.linspace(-3, 3, 13)
    np.testing.assert_allclose(rot.yaw(rot.from_yaw(theta)), theta, atol=1e-12)
