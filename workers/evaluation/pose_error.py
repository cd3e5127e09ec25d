"""AMP's pose error (Peng et al. 2021, Eq. 10), measured after dynamic time warping.

For a simulated frame with body positions x_j and a reference frame with x̂_j,

    e = 1/J · Σ_j ‖(x_j − x_root) − (x̂_j − x̂_root)‖            (metres)

over the J non-root bodies: each body's position relative to the root, so the
character's place in the world does not count. A policy that imitates a clip
need not keep the clip's timing, so AMP aligns the two sequences by dynamic
time warping with e as the local cost and reports the mean of e along the
warping path. The alignment is done by dtw-python on a precomputed cost matrix.

Everything here is plain NumPy: sequences are arrays of relative positions
[T, J, 3] made by `relative_positions`.
"""

from __future__ import annotations

import numpy as np


def relative_positions(xpos: np.ndarray, root: int = 0, heading_inverse: np.ndarray | None = None) -> np.ndarray:
    """Positions of every non-root body relative to the root body, x_j − x_root.

    xpos: [T, B, 3] body positions. heading_inverse: optional [T, 3, 3] rotations
    from world to each frame's heading frame (e.g. `workers.body.features.heading_inverse`
    of the root rotations); when given, the offsets are rotated into it. The
    evaluation passes it, so that a character whose yaw drifts away from the
    reference's is still compared by its pose rather than by its heading.
    Returns [T, B-1, 3].
    """
    xpos = np.asarray(xpos, dtype=float)
    if xpos.ndim != 3 or xpos.shape[-1] != 3 or not 0 <= root < xpos.shape[1]:
        raise ValueError(f"xpos must be [T, B, 3] with root < B, got {xpos.shape} and root={root}")
    rel = np.delete(xpos - xpos[:, root : root + 1], root, axis=1)
    if heading_inverse is None:
        return rel
    heading_inverse = np.asarray(heading_inverse, dtype=float)
    if heading_inverse.shape != (xpos.shape[0], 3, 3):
        raise ValueError(f"heading_inverse must be [T, 3, 3] = {(xpos.shape[0], 3, 3)}, got {heading_inverse.shape}")
    return np.einsum("tij,tbj->tbi", heading_inverse, rel)


def _check_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a [N, J, 3] and b [M, J, 3] as float arrays; ValueError naming the shapes otherwise."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ok = a.ndim == b.ndim == 3 and a.shape[2] == b.shape[2] == 3 and a.shape[1] == b.shape[1]
    if not ok or a.shape[0] == 0 or b.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(
            f"expected non-empty relative positions [N, J, 3] and [M, J, 3] with the same J, "
            f"got {a.shape} and {b.shape}"
        )
    return a, b


def pose_error_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Eq. 10 between every frame of a and every frame of b.

    a: [N, J, 3], b: [M, J, 3] relative positions. Returns [N, M] whose (i, k)
    entry is the mean over joints j of ‖a[i, j] − b[k, j]‖, in metres.
    Summed one joint at a time, so memory stays [N, M, 3] for long episodes.
    """
    a, b = _check_pair(a, b)
    total = np.zeros((a.shape[0], b.shape[0]))
    for j in range(a.shape[1]):
        total += np.linalg.norm(a[:, None, j] - b[None, :, j], axis=-1)
    return total / a.shape[1]


def per_frame_pose_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Eq. 10 of frame i of a against frame i of b, without time warping.

    a, b: [N, J, 3] relative positions of equal length. Returns [N], metres.
    """
    a, b = _check_pair(a, b)
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"per-frame error needs sequences of equal length, got {a.shape} and {b.shape}")
    return np.linalg.norm(a - b, axis=-1).mean(axis=-1)


def dtw_pose_error(a: np.ndarray, b: np.ndarray, step_pattern: str = "symmetric2") -> dict[str, np.ndarray | float]:
    """AMP's pose error: Eq. 10 averaged along the DTW alignment of a and b.

    a: [N, J, 3], b: [M, J, 3] relative positions; step_pattern is passed to
    dtw-python. Returns a dict with, for a path of L steps:
      "error":    mean of the cost along the warping path (float, metres)
      "per_step": [L] the Eq. 10 cost of each aligned pair
      "index_a":  [L] indices into a
      "index_b":  [L] indices into b
    """
    cost = pose_error_matrix(a, b)
    from dtw import dtw  # dtw-python (and SciPy under it) imported when an alignment is made

    alignment = dtw(cost, step_pattern=step_pattern)
    index_a, index_b = np.asarray(alignment.index1), np.asarray(alignment.index2)
    per_step = cost[index_a, index_b]
    return {"error": float(per_step.mean()), "per_step": per_step, "index_a": index_a, "index_b": index_b}


def eq10_dtw_pose_error(a_xpos: np.ndarray, b_xpos: np.ndarray, root: int = 0) -> float:
    """AMP's Eq. 10 as written, after DTW under its own cost: offsets from the root on the world axes
    (no heading frame) and 1/N_joint over all B joints of the body, the root's zero term counted.

    a_xpos: [N, B, 3], b_xpos: [M, B, 3] body positions. The per-pair cost is (B − 1)/B of the
    mean over the non-root bodies, a constant factor, so the alignment is the same.
    """
    bodies = np.asarray(a_xpos).shape[1]
    warped = dtw_pose_error(relative_positions(a_xpos, root), relative_positions(b_xpos, root))
    return warped["error"] * (bodies - 1) / bodies
