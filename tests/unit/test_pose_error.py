"""AMP's pose error (Eq. 10) with and without dynamic time warping: known answers."""

import math

import numpy as np
import pytest

from workers.body import rotations as rot
from workers.body.features import heading_inverse
from workers.evaluation.pose_error import (
    dtw_pose_error,
    eq10_dtw_pose_error,
    per_frame_pose_error,
    pose_error_matrix,
    relative_positions,
)


def clip_relative_positions(library, name: str) -> np.ndarray:
    """Every stored frame of one clip as heading-frame relative positions [T, B-1, 3]."""
    clip = library.clip_id(name)
    frames = np.arange(library.num_frames[clip])
    s = library.state(np.full(len(frames), clip), frames)
    return relative_positions(s.xpos, heading_inverse=heading_inverse(s.xquat[:, 0]))


@pytest.fixture(scope="module")
def walk(walk_run) -> np.ndarray:
    return clip_relative_positions(walk_run, "humanoid3d_walk")


@pytest.fixture(scope="module")
def run(walk_run) -> np.ndarray:
    return clip_relative_positions(walk_run, "humanoid3d_run")


# relative_positions -------------------------------------------------------------
def test_relative_positions_subtract_the_root_and_drop_it():
    xpos = np.array([[[1.0, 2.0, 3.0], [5.0, 5.0, 5.0], [1.0, 2.0, 4.0]]])  # [T=1, B=3, 3]
    np.testing.assert_allclose(relative_positions(xpos), [[[4.0, 3.0, 2.0], [0.0, 0.0, 1.0]]])
    np.testing.assert_allclose(relative_positions(xpos, root=1), [[[-4.0, -3.0, -2.0], [-4.0, -3.0, -1.0]]])


def test_relative_positions_rotate_into_the_heading_frame():
    xpos = np.array([[[0.0, 0.0, 1.0], [0.0, 1.0, 1.0]]])  # the body is 1 m along +y of the root
    # World to heading frame for a root facing +y: a yaw of −90°, taking +y to +x.
    h_inv = np.array([[[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    np.testing.assert_allclose(relative_positions(xpos, heading_inverse=h_inv), [[[1.0, 0.0, 0.0]]], atol=1e-12)


def test_heading_frame_makes_the_error_blind_to_yaw(walk_run, walk):
    s = walk_run.state(np.zeros(10, dtype=int), np.arange(10))
    turn = np.full(10, 0.7)  # the whole clip turned by 0.7 rad about the vertical
    turned_xpos = s.xpos @ rot.yaw_matrix(turn).transpose(0, 2, 1)
    turned_root = rot.mul(rot.from_yaw(turn), s.xquat[:, 0])
    turned = relative_positions(turned_xpos, heading_inverse=heading_inverse(turned_root))
    assert per_frame_pose_error(turned, walk[:10]).max() < 1e-9
    # In world coordinates the same turn is an error of 0.118 m (measured).
    assert per_frame_pose_error(relative_positions(turned_xpos), relative_positions(s.xpos)).mean() > 0.05


def test_eq10_as_written_uses_world_axes_and_every_joint():
    """Three bodies, the root at the origin in both: one body 0.3 m off. Eq. 10 divides by N_joint = 3 (the
    root's zero term counted): 0.1 m; ours divides by the two non-root bodies: 0.15 m. A yaw turn of the
    whole body costs Eq. 10 (world axes) and not ours (heading frame)."""
    ref = np.array([[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]] * 2)  # [T=2, B=3, 3]
    moved = ref.copy()
    moved[:, 1, 0] += 0.3
    assert eq10_dtw_pose_error(moved, ref) == pytest.approx(0.1)
    assert dtw_pose_error(relative_positions(moved), relative_positions(ref))["error"] == pytest.approx(0.15)
    turned = ref @ rot.yaw_matrix(np.full(2, np.pi / 2)).transpose(0, 2, 1)  # +x to +y, +y to -x
    # Offsets (1, 0, 0) -> (0, 1, 0) and (0, 1, 0) -> (-1, 0, 0): sqrt(2) each, over 3 joints.
    assert eq10_dtw_pose_error(turned, ref) == pytest.approx(2 * np.sqrt(2) / 3)


# pose_error_matrix, per_frame_pose_error, dtw_pose_error on a hand-worked example ---
def test_two_joint_example_by_hand():
    a = np.array(
        [
            [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
            [[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]],
        ]
    )  # [N=2, J=2, 3]
    b = np.array(
        [
            [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
            [[3.0, 4.0, 0.0], [1.0, 0.0, 0.0]],
        ]
    )  # [M=2, J=2, 3]
    # (0, 0): joint 0 ‖0‖ = 0,        joint 1 ‖0‖ = 0                     → 0
    # (0, 1): joint 0 ‖(−3, −4, 0)‖ = 5, joint 1 0                        → 5/2
    # (1, 0): joint 0 0,              joint 1 ‖(−1, 2, 0)‖ = √5          → √5/2 ≈ 1.118
    # (1, 1): joint 0 5,              joint 1 √5                          → (5 + √5)/2 ≈ 3.618
    r5 = math.sqrt(5.0)
    expected = np.array([[0.0, 2.5], [r5 / 2, (5 + r5) / 2]])
    np.testing.assert_allclose(pose_error_matrix(a, b), expected, rtol=1e-12)
    np.testing.assert_allclose(per_frame_pose_error(a, b), [0.0, (5 + r5) / 2], rtol=1e-12)
    # symmetric2 weighs a diagonal step twice: the three paths from (0, 0) to (1, 1) cost
    # diagonal 0 + 2·3.618 = 7.236, via (0, 1) 0 + 2.5 + 3.618 = 6.118, via (1, 0) 0 + 1.118 + 3.618 = 4.736.
    out = dtw_pose_error(a, b)
    np.testing.assert_array_equal(out["index_a"], [0, 1, 1])
    np.testing.assert_array_equal(out["index_b"], [0, 0, 1])
    np.testing.assert_allclose(out["per_step"], [0.0, r5 / 2, (5 + r5) / 2], rtol=1e-12)
    assert out["error"] == pytest.approx((5 + 2 * r5) / 6, rel=1e-12)  # ≈ 1.579


def test_matrix_matches_a_loop_over_frames():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(7, 4, 3)), rng.normal(size=(5, 4, 3))
    slow = [[np.mean([np.linalg.norm(a[i, j] - b[k, j]) for j in range(4)]) for k in range(5)] for i in range(7)]
    np.testing.assert_allclose(pose_error_matrix(a, b), slow, rtol=1e-12)
    np.testing.assert_allclose(per_frame_pose_error(a[:5], b), np.diag(slow), rtol=1e-12)


# Constant offset of one joint: d / J -------------------------------------------------
def test_offset_of_one_joint_costs_d_over_j(walk):
    d, j = 0.1, walk.shape[1]  # J = 14 non-root bodies
    moved = walk.copy()
    moved[:, 3] += d * np.array([0.6, 0.0, 0.8])  # a unit direction
    np.testing.assert_allclose(per_frame_pose_error(walk, moved), d / j, rtol=1e-9)


def test_offset_of_one_joint_costs_d_over_j_after_dtw():
    # Frames far apart from each other, so the best alignment is the identity.
    rng = np.random.default_rng(1)
    a = rng.normal(size=(20, 5, 3))
    d = 0.25
    b = a.copy()
    b[:, 2, 1] += d
    out = dtw_pose_error(a, b)
    np.testing.assert_array_equal(out["index_a"], np.arange(20))
    np.testing.assert_array_equal(out["index_b"], np.arange(20))
    assert out["error"] == pytest.approx(d / 5, rel=1e-9)


# The walk clip against time-warped copies of itself, and against the run ---------------
def test_walk_against_a_repetition_warped_copy_of_itself(walk):
    # Two monotone time maps of the same length (57 frames) that both visit every one of the
    # 38 frames: a plays the first half at half speed, b the second half.
    n, h = len(walk), len(walk) // 2
    a = walk[np.sort(np.concatenate([np.arange(n), np.arange(h)]))]
    b = walk[np.sort(np.concatenate([np.arange(n), np.arange(h, 2 * h)]))]
    assert a.shape == b.shape == (n + h, 14, 3)
    out = dtw_pose_error(a, b)
    # Measured: DTW 0.0 m; frame against frame 0.079 m.
    assert out["error"] < 1e-6
    assert per_frame_pose_error(a, b).mean() > 0.05
    assert out["index_a"][0] == out["index_b"][0] == 0
    assert out["index_a"][-1] == out["index_b"][-1] == n + h - 1
    assert np.all(np.diff(out["index_a"]) >= 0) and np.all(np.diff(out["index_b"]) >= 0)


def test_walk_against_a_repeat_and_skip_warped_copy_of_itself(walk):
    # Same length, time map t^1.6: early frames repeated, late frames skipped.
    n = len(walk)
    idx = np.round((n - 1) * np.linspace(0.0, 1.0, n) ** 1.6).astype(int)
    assert np.all(np.diff(idx) >= 0) and len(np.unique(idx)) < n
    warped = walk[idx]
    out = dtw_pose_error(walk, warped)
    # Measured: DTW 0.0018 m (only the skipped frames cost, and neighbouring frames differ
    # by 0.015 m on average); frame against frame 0.060 m.
    assert out["error"] < 0.005
    assert per_frame_pose_error(walk, warped).mean() > 0.04


def test_walk_against_run_is_a_large_error(walk, run):
    out = dtw_pose_error(walk, run)  # 38 against 24 frames
    # Measured: 0.153 m (symmetric2), 0.145 m (asymmetric).
    assert out["error"] > 0.1
    assert dtw_pose_error(walk, run, step_pattern="asymmetric")["error"] > 0.1
    assert len(out["per_step"]) == len(out["index_a"]) == len(out["index_b"]) >= 38


# Bad input ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("a_shape", "b_shape"),
    [
        ((0, 4, 3), (5, 4, 3)),  # empty a
        ((5, 4, 3), (0, 4, 3)),  # empty b
        ((5, 4, 3), (5, 3, 3)),  # joint counts differ
        ((5, 4, 2), (5, 4, 2)),  # not 3-D points
        ((5, 12), (5, 12)),  # flattened
    ],
)
def test_bad_shapes_raise_naming_them(a_shape, b_shape):
    a, b = np.zeros(a_shape), np.zeros(b_shape)
    for fn in (pose_error_matrix, dtw_pose_error):
        with pytest.raises(ValueError, match=f"{a_shape}.*{b_shape}".replace("(", r"\(").replace(")", r"\)")):
            fn(a, b)


def test_per_frame_needs_equal_lengths():
    with pytest.raises(ValueError, match=r"\(5, 4, 3\).*\(6, 4, 3\)"):
        per_frame_pose_error(np.zeros((5, 4, 3)), np.zeros((6, 4, 3)))


def test_relative_positions_reject_bad_input():
    with pytest.raises(ValueError, match="root"):
        relative_positions(np.zeros((4, 3, 3)), root=3)
    with pytest.raises(ValueError, match=r"\(4, 3\)"):
        relative_positions(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="heading_inverse"):
        relative_positions(np.zeros((4, 3, 3)), heading_inverse=np.zeros((3, 3, 3)))
