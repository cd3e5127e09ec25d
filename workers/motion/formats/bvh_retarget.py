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
# Limb planes that give the twist of the limbs' corrections (limb_twists): (upper, middle) bodies,
# whose bones span the plane, and the bodies corrected from it. A mean normal under MIN_BEND
# (the mean sine of the bend, about 3 degrees) is a limb held straight, one under MIN_STEADY of the
# normals' mean length a plane that turns about in the body's frame (a knee bending sideways as
# much as back): no twist is read from either. The LaFAN1, Mixamo and mocap-bank clips keep 0.99.
LIMB_PLANES = (
    (("hip", "knee"), ("hip", "knee")),
    (("shoulder", "elbow"), ("shoulder", "elbow")),
    (("knee", "ankle"), ("ankle",)),
)
MIN_BEND = 0.05
MIN_STEADY = 0.9
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


def rest_corrections(
    character: Character, joints: list, rest: np.ndarray, src: dict, motion: tuple | None = None
) -> dict:
    """Body index -> quaternion C with G_ours = G_source C, for every mapped body (see bvh's module doc).

    joints: the source's joints (bvh.Joint: .parent, in hierarchy order); rest: their rest positions
    [J, 3] in our axes (z-up); src: our body name -> source joint index (bvh_names.match_joints);
    motion: the source's global rotations (joint index -> [T, 3, 3], at least the mapped joints) and
    positions [T, J, 3], in our axes, from which the limbs' twists are read (`limb_twists`); None
    keeps the rest pose's guess.
    """
    names, (parent, _) = character.body_names, tree(character)
    body_pos = character.model.body_pos[1:]
    ours = np.zeros_like(body_pos)  # our rest positions (all body_quat are identity)
    for b in range(len(names)):
        ours[b] = body_pos[b] + (ours[parent[b]] if parent[b] >= 0 else 0.0)
    bone = _bones(character, joints, rest, src)

    def theirs(b: int) -> np.ndarray:
        tip = bone[b][1]
        return rest[tip].mean(axis=0) - rest[src[names[b]]] if tip else np.zeros(3)

    facing = _IDENTITY  # turns our rest frame (spine up, hips left to right) onto the source's
    if {"left_hip", "right_hip"} <= set(src):
        up_ours, up_src, lat_src = bone[0][0], theirs(0), rest[src["left_hip"]] - rest[src["right_hip"]]
        tilt, axis = swing(up_ours, up_src), up_src / max(np.linalg.norm(up_src), 1e-12)
        lat = rot.rotate(tilt, ours[names.index("left_hip")] - ours[names.index("right_hip")])
        yaw = np.arctan2(np.cross(lat, lat_src) @ axis, lat @ lat_src - (lat @ axis) * (lat_src @ axis))
        facing = rot.mul(rot.from_expmap(yaw * axis), tilt)
    out = {}
    for b in (b for b, name in enumerate(names) if name in src):
        out[b] = rot.mul(swing(rot.rotate(facing, bone[b][0]), theirs(b)), facing)
    if motion is not None:
        out.update(limb_twists(character, rest, src, bone, out, *motion))
    return out


def _bones(character: Character, joints: list, rest: np.ndarray, src: dict) -> dict:
    """Mapped body b -> (our rest bone [3], the source joints whose mean position ends its bone).

    A bone goes to the first child (for the source: the joint matched to it, across unmatched
    joints and past a zero-length one), else to the mean of the children (our End Site for our
    leaves); an empty list where the source joint has no children.
    """
    names, (_, kids) = character.body_names, tree(character)
    body_pos = character.model.body_pos[1:]

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

    out = {}
    for b in (b for b, name in enumerate(names) if name in src):
        s = src[names[b]]
        child = src.get(names[kids[b][0]]) if kids[b] else None
        if child is not None and is_below(child, s):
            out[b] = (body_pos[kids[b][0]], [onward(child, s)])
            continue
        mine = body_pos[kids[b]].mean(axis=0) if kids[b] else np.asarray(END_SITES.get(names[b], (0.0, 0.0, 0.0)))
        out[b] = (mine, [j for j, jt in enumerate(joints) if jt.parent == s])
    return out


def limb_twists(
    character: Character, rest: np.ndarray, src: dict, bone: dict, corr: dict, rots: dict, pos: np.ndarray
) -> dict:
    """The limbs' corrections `corr` (body index -> quaternion) turned about their bones as the motion shows.

    A bone's rest direction leaves its twist open: a source whose rest pose has the legs along
    the spine (LaFAN1's, every bone along its joint's x axis) turns them by half a turn about an
    axis the rest pose does not tell, and its feet come out upside down. The plane of a limb
    tells, over the clip: for each of LIMB_PLANES (thigh-shin, upper arm-forearm, shin-foot), the
    mean over the frames of the normal (upper x lower bone, unit bones) in the frame of each body
    it corrects is matched to ours: our middle hinge bent towards the longer side of its range
    (knees back, elbows forward), or our rest pose where the middle is a ball (the ankle). The
    correction then takes our bone and that normal onto the source's. A ball's plane also turns
    with the joint's own roll, so there the turn is rounded to a whole half turn (which way up
    the foot is). A plane held straight or turning about (MIN_BEND, MIN_STEADY) keeps `corr`.
    """
    names, model = character.body_names, character.model
    out = {}
    for side in ("left", "right"):
        for (upper, middle), fixed in LIMB_PLANES:
            u, m = names.index(f"{side}_{upper}"), names.index(f"{side}_{middle}")
            if u not in bone or m not in bone or not bone[u][1] or not bone[m][1]:
                continue
            bend = None  # our middle body's rotation in the pose the plane is read from; None for a ball
            j = next((j for j, body in enumerate(character.body_of_joint) if body == m), None)
            if j is not None and character.joint_types[j] == "hinge":
                jid = model.joint(character.joint_names[j]).id
                lo, hi = model.jnt_range[jid] if model.jnt_limited[jid] else (0.0, 1.0)
                bend = rot.from_expmap(np.pi / 2 * (1.0 if abs(hi) > abs(lo) else -1.0) * model.jnt_axis[jid])
            normal = np.cross(bone[u][0], rot.rotate(_IDENTITY if bend is None else bend, bone[m][0]))
            upper_v = pos[:, bone[u][1]].mean(axis=1) - pos[:, src[names[u]]]
            lower_v = pos[:, bone[m][1]].mean(axis=1) - pos[:, src[names[m]]]
            n = np.cross(upper_v, lower_v)
            n /= (
                np.linalg.norm(upper_v, axis=-1, keepdims=True) * np.linalg.norm(lower_v, axis=-1, keepdims=True)
                + 1e-12
            )
            steady = np.linalg.norm(n, axis=-1).mean()
            for body in (names.index(f"{side}_{kind}") for kind in fixed):
                s = src[names[body]]
                n_src = np.einsum("tij,ti->j", rots[s], n) / len(n)  # G^T n, the mean over the frames
                if np.linalg.norm(n_src) < max(MIN_BEND, MIN_STEADY * steady):
                    continue
                mine = normal if body == u or bend is None else rot.rotate(rot.conj(bend), normal)
                tip = rest[bone[body][1]].mean(axis=0) - rest[s]
                turned = rot.from_matrix(_frame(tip, n_src) @ _frame(bone[body][0], mine).T)
                if bend is None:  # a whole half turn about the source's bone, or none
                    d = rot.mul(turned, rot.conj(corr[body]))
                    half = np.round(2.0 * np.arctan2(d[1:] @ tip, d[0] * np.linalg.norm(tip)) / np.pi)
                    turned = rot.mul(rot.from_expmap(half * np.pi * tip / np.linalg.norm(tip)), corr[body])
                out[body] = turned
    return out


def _frame(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Orthonormal columns: first's direction, second's part across it, their cross product."""
    e1 = first / max(np.linalg.norm(first), 1e-12)
    e2 = second - (second @ e1) * e1
    e2 = e2 / max(np.linalg.norm(e2), 1e-12)
    return np.stack((e1, e2, np.cross(e1, e2)), axis=1)


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
