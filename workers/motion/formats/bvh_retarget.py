"""Retargeting a BVH skeleton's motion onto our character: rest-pose corrections and grounding.

Used by `workers.motion.formats.bvh.load`; see its module doc for the whole import.
"""

from __future__ import annotations

import mujoco
import numpy as np

from workers.body import rotations as rot
from workers.body.character import Character

# End Sites of our leaf bodies in the body frame (z-up, metres): the top of the
# head sphere, the far side of the hand spheres, the front bottom edge of the feet.
END_SITES = {
    "neck": (0.0, 0.0, 0.2775), "right_wrist": (0.0, 0.0, -0.04), "left_wrist": (0.0, 0.0, -0.04),
    "right_ankle": (0.1335, 0.0, -0.05), "left_ankle": (0.1335, 0.0, -0.05),
}  # fmt: skip
# Grounding: the 5th percentile over the frames of the character's lowest point (in
# practice a foot) goes to GROUND_HEIGHT. Measured the same way (at the source frames),
# the bundled walks sit there: humanoid3d_walk -0.40 cm, walker/0walk_forward -0.07,
# turn_left0 +0.16, turn_left1 +0.26, turn_right0 -0.25, turn_right1 -0.25 (mean -0.09 cm),
# with their lowest frame 0.1 to 0.6 cm lower. A percentile rather than the minimum, so
# that one frame of a toe-off (our rigid box foot pitched on its corner) or of noisy
# data does not lift the whole clip.
GROUND_HEIGHT = 0.0
GROUND_PERCENTILE = 5.0
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def tree(character: Character) -> tuple[np.ndarray, list[list[int]]]:
    """Parent of each body (-1 for the root) and the children of each body, in model order."""
    parent = character.model.body_parentid[1:] - 1
    return parent, [[c for c in range(1, len(parent)) if parent[c] == b] for b in range(len(parent))]


def swing(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation (quaternion) taking direction u to direction v; identity if either is zero."""
    nu, nv = np.linalg.norm(u), np.linalg.norm(v)
    if nu < 1e-9 or nv < 1e-9:
        return _IDENTITY
    u, v = u / nu, v / nv
    if u @ v < -1.0 + 1e-12:  # opposite: half a turn about any perpendicular axis
        axis = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
        return np.concatenate(([0.0], axis / np.linalg.norm(axis)))
    return rot.normalize(np.concatenate(([1.0 + u @ v], np.cross(u, v))))


def rest_corrections(character: Character, joints: list, rest: np.ndarray, src: dict) -> dict:
    """Body index -> quaternion C with G_ours = G_source C, for every mapped body (see bvh's module doc).

    joints: the source's joints (bvh.Joint: .parent, in hierarchy order); rest: their rest positions
    [J, 3] in our axes (z-up); src: our body name -> source joint index (bvh_names.match_joints).
    """
    names, (parent, kids) = character.body_names, tree(character)
    body_pos = character.model.body_pos[1:]
    ours = np.zeros_like(body_pos)  # our rest positions (all body_quat are identity)
    for b in range(len(names)):
        ours[b] = body_pos[b] + (ours[parent[b]] if parent[b] >= 0 else 0.0)

    def is_below(j: int, anc: int) -> bool:
        while j >= 0 and j != anc:
            j = joints[j].parent
        return j == anc

    tiny = 1e-6 * max(float(np.ptp(rest)), 1e-9)

    def onward(j: int, s: int) -> int:
        """j, or where a zero-length joint at s leads (CMU's Neck sits on Spine1: Neck1 then)."""
        while np.linalg.norm(rest[j] - rest[s]) < tiny:
            below = [c for c, jt in enumerate(joints) if jt.parent == j]
            if not below:
                break
            j = below[0]
        return j

    def bones(b: int) -> tuple[np.ndarray, np.ndarray]:
        """Our and the source's rest bone vectors for body b."""
        s = src[names[b]]
        if kids[b]:
            child = src.get(names[kids[b][0]])
            if child is not None and is_below(child, s):
                return body_pos[kids[b][0]], rest[onward(child, s)] - rest[s]
        # Without a matched first child: the mean of the children's offsets, ours and the source's.
        mine = body_pos[kids[b]].mean(axis=0) if kids[b] else np.asarray(END_SITES.get(names[b], (0.0, 0.0, 0.0)))
        direct = [j for j, jt in enumerate(joints) if jt.parent == s]
        return mine, (rest[direct].mean(axis=0) - rest[s]) if direct else np.zeros(3)

    facing = _IDENTITY  # turns our rest frame (spine up, hips left to right) onto the source's
    if {"left_hip", "right_hip"} <= set(src):
        (up_ours, up_src), lat_src = bones(0), rest[src["left_hip"]] - rest[src["right_hip"]]
        tilt, axis = swing(up_ours, up_src), up_src / max(np.linalg.norm(up_src), 1e-12)
        lat = rot.rotate(tilt, ours[names.index("left_hip")] - ours[names.index("right_hip")])
        yaw = np.arctan2(np.cross(lat, lat_src) @ axis, lat @ lat_src - (lat @ axis) * (lat_src @ axis))
        facing = rot.mul(rot.from_expmap(yaw * axis), tilt)
    out = {}
    for b in (b for b, name in enumerate(names) if name in src):
        mine, theirs = bones(b)
        out[b] = rot.mul(swing(rot.rotate(facing, mine), theirs), facing)
    return out


def lowest_points(character: Character, qpos: np.ndarray) -> np.ndarray:
    """Height [T] of the character's lowest point in each frame (every geom of a body; unit quaternions).

    Boxes by their corners, spheres and capsules exactly, anything else by its bounding sphere
    (as workers.motion.clip.geom_min_z, here for all frames at once).
    """
    model, data = character.model, mujoco.MjData(character.model)
    geoms = np.flatnonzero(model.geom_bodyid > 0)
    pos, mat = np.zeros((len(qpos), len(geoms), 3)), np.zeros((len(qpos), len(geoms), 9))
    for t, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        pos[t], mat[t] = data.geom_xpos[geoms], data.geom_xmat[geoms]
    size, kind = model.geom_size[geoms], model.geom_type[geoms]
    zrow = np.abs(mat[..., 6:9])  # |z components| of the geom's axes
    drop = np.broadcast_to(model.geom_rbound[geoms], zrow.shape[:2]).copy()
    box, sphere = kind == mujoco.mjtGeom.mjGEOM_BOX, kind == mujoco.mjtGeom.mjGEOM_SPHERE
    capsule = kind == mujoco.mjtGeom.mjGEOM_CAPSULE
    drop[:, box] = (zrow[:, box] * size[box]).sum(axis=-1)
    drop[:, sphere] = size[sphere, 0]
    drop[:, capsule] = zrow[:, capsule, 2] * size[capsule, 1] + size[capsule, 0]
    return (pos[..., 2] - drop).min(axis=1)


def ground_shift(character: Character, qpos: np.ndarray, height: float = GROUND_HEIGHT) -> float:
    """The vertical shift (m) that puts the GROUND_PERCENTILE of `lowest_points` at `height`."""
    return float(height - np.percentile(lowest_points(character, qpos), GROUND_PERCENTILE))
