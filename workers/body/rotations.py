"""Vectorised rotation maths on NumPy arrays.

Quaternions are (w, x, y, z), MuJoCo's convention, and every function works on
arrays with any number of leading dimensions: a quaternion array has shape
[..., 4], a vector array [..., 3], a matrix array [..., 3, 3].
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions [..., 4]."""
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion) [..., 4]."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b; broadcasts over leading dimensions."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        axis=-1,
    )


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v [..., 3] by unit quaternions q [..., 4]."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] from unit quaternions [..., 4]."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    m = np.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        axis=-1,
    )  # fmt: skip
    return m.reshape(q.shape[:-1] + (3, 3))


def from_matrix(m: np.ndarray) -> np.ndarray:
    """Unit quaternions [..., 4] (w >= 0) from rotation matrices [..., 3, 3]."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # Each candidate is 4x one component times the quaternion; pick the best-conditioned.
    cands = np.stack(
        (
            np.stack((1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2],
                      m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]), -1),
            np.stack((m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22,
                      m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]), -1),
            np.stack((m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0],
                      1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]), -1),
            np.stack((m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                      m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22), -1),
        ),
        axis=-2,
    )  # fmt: skip
    best = np.argmax(np.stack((1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                               1 - m00 + m11 - m22, 1 - m00 - m11 + m22), -1), -1)  # fmt: skip
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def to_6d(m: np.ndarray) -> np.ndarray:
    """The first two columns of rotation matrices [..., 3, 3], flattened to [..., 6].

    Order: (m00, m10, m20, m01, m11, m21), column by column.
    """
    return np.concatenate((m[..., :, 0], m[..., :, 1]), axis=-1)


def from_expmap(v: np.ndarray) -> np.ndarray:
    """Unit quaternions [..., 4] from rotation vectors (axis * angle) [..., 3]."""
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle, with its limit 1/2 at zero.
    scale = np.where(angle > 1e-8, np.sin(half) / np.maximum(angle, _EPS), 0.5 - angle**2 / 48.0)
    return np.concatenate((np.cos(half), v * scale), axis=-1)


def to_expmap(q: np.ndarray) -> np.ndarray:
    """Rotation vectors [..., 3] (angle in [0, pi]) from unit quaternions [..., 4]."""
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    scale = np.where(s > 1e-8, angle / np.maximum(s, _EPS), 2.0)
    return q[..., 1:] * scale


def angle(q: np.ndarray) -> np.ndarray:
    """Rotation angle in [0, pi] of unit quaternions [..., 4]."""
    return 2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0]))


def slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical interpolation between unit quaternions a and b [..., 4] at t [...] in [0, 1]."""
    t = np.asarray(t, dtype=float)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    safe = np.where(near, 1.0, sin_theta)
    wa = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    wb = np.where(near, t, np.sin(t * theta) / safe)
    return normalize(wa * a + wb * b)


def yaw(q: np.ndarray) -> np.ndarray:
    """Heading angle [...] of unit quaternions: the yaw of the rotated x axis about world z."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def from_yaw(theta: np.ndarray) -> np.ndarray:
    """Quaternions [..., 4] of rotations by theta [...] about world z."""
    theta = np.asarray(theta, dtype=float)
    zero = np.zeros_like(theta)
    return np.stack((np.cos(0.5 * theta), zero, zero, np.sin(0.5 * theta)), axis=-1)


def yaw_matrix(theta: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] about world z by theta [...]."""
    c, s = np.cos(theta), np.sin(theta)
    z, o = np.zeros_like(theta), np.ones_like(theta)
    return np.stack((c, -s, z, s, c, z, z, z, o), axis=-1).reshape(np.shape(theta) + (3, 3))
