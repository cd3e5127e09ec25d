"""BVH motion capture files: export on our skeleton, import with retargeting.

`save` writes our bodies as the HIERARCHY (End Sites after the neck, wrists and
ankles), y-up (x forward, y up, z right, as DeepMimic), in CENTIMETRES: the root
with Xposition Yposition Zposition Zrotation Xrotation Yrotation (OFFSET zero,
absolute position), the other bodies with Zrotation Xrotation Yrotation, degrees;
hinges as the rotation about their axis, welded bodies (the wrists) as zeros.

`load` reads any BVH (any channel order, position channels on any joint, End Sites,
any whitespace, one frame a line). Rotation channels compose in the order listed
(`Zrotation Xrotation Yrotation` is Rz Rx Ry); position channels replace their
components of the OFFSET. It then retargets onto our character:

* `joint_map` (default `DEFAULT_JOINT_MAP`, case-insensitive, a `namespace:`
  prefix ignored) matches source joints to our bodies, the first in hierarchy
  order where several match one body. Our root must be matched; our other joints
  without a source keep the identity rotation.
* Per body, G_ours = G_source C: the source joint's global orientation and a
  rest-pose correction C, the facing alignment F (our rest frame, spine up and hips
  left to right, onto the source's) then the smallest rotation taking our rest
  bone, turned by F, onto the source's. A bone goes to the first child (for the
  source: the joint matched to it, across unmatched joints) or, for our leaves, to
  the End Site (for the source: the mean of its children's offsets). Files from
  `save` import with identity corrections. Hinges keep the twist about their axis.
* The root position is the matched source joint's (metres, z-up), as is: a source
  whose hips are higher or lower than ours is not rescaled.

`scale` (metres per file unit) defaults to a guess from the rest pose's height:
up to 10 units metres, up to 400 centimetres (what `save` writes), beyond that
millimetres. Files in inches or other units need an explicit `scale`.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from workers.motion.clip import RawClip, interpolate_qpos, normalize_quats
from workers.motion.errors import ClipError
from workers.motion.formats.deepmimic import Y_TO_Z
from workers.sim import rotations as rot
from workers.sim.character import Character

log = logging.getLogger(__name__)

SAVE_UNITS_PER_METRE = 100.0  # `save` writes centimetres
SAVE_ROTATION_ORDER = "ZXY"
# End Sites of our leaf bodies in the body frame (z-up, metres): the top of the
# head sphere, the far side of the hand spheres, the front bottom edge of the feet.
END_SITES = {
    "neck": (0.0, 0.0, 0.2775), "right_wrist": (0.0, 0.0, -0.04), "left_wrist": (0.0, 0.0, -0.04),
    "right_ankle": (0.1335, 0.0, -0.05), "left_ankle": (0.1335, 0.0, -0.05),
}  # fmt: skip
# Source joint name (case-insensitive) -> our body. "LeftShoulder" is left out on
# purpose: in LaFAN1, CMU and Mixamo it is the clavicle, and the upper arm is LeftArm.
_LIMB_NAMES = {
    "hip": ("UpLeg", "Thigh", "Hip"), "knee": ("Leg", "Shin", "Knee"), "ankle": ("Foot", "Ankle"),
    "shoulder": ("Arm", "UpArm", "UpperArm"), "elbow": ("ForeArm", "LowArm", "LowerArm", "Elbow"),
    "wrist": ("Hand", "Wrist"),
}  # fmt: skip
DEFAULT_JOINT_MAP: dict[str, str] = {
    "root": "root", "chest": "chest", "neck": "neck", "Hips": "root", "Pelvis": "root",
    "Spine": "chest", "Spine1": "chest", "Chest": "chest", "Neck": "neck", "Head": "neck",
    **{f"{s}_{b}": f"{s}_{b}" for s in ("right", "left") for b in _LIMB_NAMES},
    **{f"{s.title()}{n}": f"{s}_{b}" for s in ("right", "left") for b, v in _LIMB_NAMES.items() for n in v},
}  # fmt: skip

_AXES = {"X": 0, "Y": 1, "Z": 2}
_CHANNELS = {f"{a}{kind}".lower(): f"{a}{kind}" for a in "XYZ" for kind in ("position", "rotation")}
_POSITIONS = "Xposition Yposition Zposition"
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


# Euler angles --------------------------------------------------------------
def axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    """Matrices [..., 3, 3] of rotations by angle [...] (radians) about coordinate axis 0, 1 or 2."""
    return rot.to_matrix(rot.from_expmap(np.asarray(angle, dtype=float)[..., None] * np.eye(3)[axis]))


def euler_to_matrix(degrees: np.ndarray, order: str) -> np.ndarray:
    """R = R_order[0] R_order[1] ... from angles [..., len(order)] in degrees (BVH's convention)."""
    rad = np.deg2rad(np.asarray(degrees, dtype=float))
    m = np.broadcast_to(np.eye(3), rad.shape[:-1] + (3, 3))
    for k, a in enumerate(order.upper()):
        m = m @ axis_rotation(_AXES[a], rad[..., k])
    return m


def matrix_to_euler(m: np.ndarray, order: str) -> np.ndarray:
    """Angles [..., 3] in degrees with euler_to_matrix(angles, order) == m, for three distinct axes.

    The middle angle is in [-90, 90]; at gimbal lock the last angle takes up what the first leaves.
    """
    if sorted(order.upper()) != ["X", "Y", "Z"]:
        raise ValueError(f"order must name three distinct axes, got {order!r}")
    i, j, k = (_AXES[a] for a in order.upper())
    s = 1.0 if (j - i) % 3 == 1 else -1.0
    b = np.arctan2(s * m[..., i, k], np.hypot(m[..., i, i], m[..., i, j]))
    a = np.arctan2(-s * m[..., j, k], m[..., k, k])
    rest = np.swapaxes(axis_rotation(i, a) @ axis_rotation(j, b), -1, -2) @ m  # R_k(c)
    p, q = (k + 1) % 3, (k + 2) % 3
    return np.rad2deg(np.stack((a, b, np.arctan2(rest[..., q, p], rest[..., p, p])), axis=-1))


# Export --------------------------------------------------------------------
def _tree(character: Character) -> tuple[np.ndarray, list[list[int]]]:
    """Parent of each body (-1 for the root) and the children of each body, in model order."""
    parent = character.model.body_parentid[1:] - 1
    return parent, [[c for c in range(1, len(parent)) if parent[c] == b] for b in range(len(parent))]


def _uniform(character: Character, raw: RawClip, fps: float | None) -> tuple[np.ndarray, float]:
    """qpos at evenly spaced frames (1 / fps apart, by default the clip's mean step) and the frame time."""
    n, t = raw.qpos.shape[0], raw.times - raw.times[0]
    dt = 1.0 / fps if fps else float(t[-1]) / (n - 1) if n > 1 else 1.0 / 30.0
    times = np.arange(int(np.floor(t[-1] / dt + 1e-6)) + 1) * dt
    if len(times) == n and np.abs(times - t).max() <= 1e-6:
        return raw.qpos, dt
    return interpolate_qpos(character, raw, times + raw.times[0]), dt


def save(character: Character, raw: RawClip, path: str | Path, fps: float | None = None) -> None:
    """Write a clip as a BVH of our skeleton (y-up, centimetres, ZXY Euler angles in degrees).

    fps: resample to this rate; by default the clip's own (evenly spaced) frames are written.
    """
    model = character.model
    qpos, dt = _uniform(character, raw, fps)
    qpos = normalize_quats(character, qpos)
    parent, kids = _tree(character)
    joint_of_body = {int(b): j for j, b in enumerate(character.body_of_joint)}
    rotations = " ".join(f"{a}rotation" for a in SAVE_ROTATION_ORDER)
    lines, order = ["HIERARCHY"], []

    def fmt(v: np.ndarray) -> str:
        return " ".join(f"{x:.10g}" for x in v)

    def write(b: int, pad: str) -> None:
        order.append(b)
        name, offset = character.body_names[b], Y_TO_Z.T @ model.body_pos[b + 1] * SAVE_UNITS_PER_METRE
        kind, channels = ("ROOT", f"6 {_POSITIONS} {rotations}") if b == 0 else ("JOINT", f"3 {rotations}")
        offset = fmt(offset if b else np.zeros(3))
        lines.append(f"{pad}{kind} {name}\n{pad}{{\n{pad}  OFFSET {offset}\n{pad}  CHANNELS {channels}")
        for c in kids[b]:
            write(c, pad + "  ")
        if not kids[b]:
            end = Y_TO_Z.T @ np.asarray(END_SITES.get(name, (0.0, 0.0, 0.0))) * SAVE_UNITS_PER_METRE
            lines.extend([f"{pad}  End Site", pad + "  {", f"{pad}    OFFSET {fmt(end)}", pad + "  }"])
        lines.append(pad + "}")

    write(0, "")
    n = qpos.shape[0]
    cols = [qpos[:, :3] @ Y_TO_Z * SAVE_UNITS_PER_METRE]
    for b in order:
        j = joint_of_body.get(b)
        if parent[b] < 0:
            q = qpos[:, 3:7]
        elif j is None:
            q = np.tile(_IDENTITY, (n, 1))
        elif character.joint_types[j] == "ball":
            q = qpos[:, character.joint_qpos[j]]
        else:
            axis = model.jnt_axis[model.joint(character.joint_names[j]).id]
            q = rot.from_expmap(qpos[:, character.joint_qpos[j].start, None] * axis)
        q_yup = np.concatenate((q[:, :1], q[:, 1:] @ Y_TO_Z), axis=-1)
        cols.append(matrix_to_euler(rot.to_matrix(q_yup), SAVE_ROTATION_ORDER))
    lines += ["MOTION", f"Frames: {n}", f"Frame Time: {float(dt)!r}"]
    lines += [fmt(row) for row in np.concatenate(cols, axis=1)]
    Path(path).write_text("\n".join(lines) + "\n")


# Parsing -------------------------------------------------------------------
@dataclass
class Joint:
    """A joint (or End Site) of a BVH skeleton; joints come in hierarchy order (parents first)."""

    name: str
    parent: int
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    channels: list[str] = field(default_factory=list)  # canonical names, e.g. "Zrotation"
    column: int = 0  # index of its first channel in a frame
    end_site: bool = False


def _parse_hierarchy(path: Path, tokens: list[str]) -> tuple[list[Joint], int]:
    """The joints and the number of channels a frame, from the tokens after HIERARCHY."""
    joints: list[Joint] = []
    stack: list[int] = []
    ncols, it = 0, iter(tokens)

    def take(what: str) -> str:
        tok = next(it, None)
        if tok is None:
            raise ClipError(path, f"HIERARCHY: the file ends where {what} was expected")
        return tok

    for tok in it:
        key, cur = tok.upper(), joints[stack[-1]] if stack else None
        if key in ("ROOT", "JOINT", "END") and (key == "ROOT") == (cur is None):
            name = f"{cur.name}/End Site" if key == "END" else take("a joint name")
            brace = take("'{'")
            if key == "END" and brace.upper() == "SITE":
                brace = take("'{'")
            if brace != "{":
                raise ClipError(path, f"HIERARCHY: expected '{{' after {tok} {name}, got {brace!r}")
            joints.append(Joint(name, stack[-1] if stack else -1, end_site=key == "END"))
            stack.append(len(joints) - 1)
        elif key == "OFFSET" and cur is not None:
            vals = [take("an OFFSET value") for _ in range(3)]
            try:
                cur.offset = np.array(vals, dtype=float)
            except ValueError:
                raise ClipError(path, f"HIERARCHY: bad OFFSET of {cur.name}: {' '.join(vals)}") from None
        elif key == "CHANNELS" and cur is not None:
            count = take("a channel count")
            names = [take("a channel name") for _ in range(int(count))] if count.isdigit() else [count]
            if any(c.lower() not in _CHANNELS for c in names):
                raise ClipError(path, f"HIERARCHY: bad CHANNELS of {cur.name}: {count} {' '.join(names)}")
            cur.channels = [_CHANNELS[c.lower()] for c in names]
            cur.column, ncols = ncols, ncols + len(names)
        elif key == "}" and cur is not None:
            stack.pop()
        else:
            raise ClipError(path, f"HIERARCHY: unexpected {tok!r}")
    if stack or not joints or ncols == 0:
        what = f"{joints[stack[-1]].name} is not closed with '}}'" if stack else "no joints or no channels"
        raise ClipError(path, f"HIERARCHY: {what}")
    return joints, ncols


def parse(path: str | Path) -> tuple[list[Joint], np.ndarray, float]:
    """The skeleton, the frames [T, channels] and the frame time (s) of a BVH file."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ClipError(path, f"cannot read as text ({e})") from None
    words = [line.split() for line in lines]
    filled = [i for i, w in enumerate(words) if w]
    if not filled or words[filled[0]][0].upper() != "HIERARCHY":
        raise ClipError(path, "no HIERARCHY section (not a BVH file)")
    motion = next((i for i in filled if words[i][0].upper() == "MOTION"), None)
    if motion is None:
        raise ClipError(path, "no MOTION section")
    joints, ncols = _parse_hierarchy(path, [t for w in words[filled[0] : motion] for t in w][1:])
    after = [i for i in filled if i > motion]
    head = [" ".join(words[i]) for i in after[:2]] + ["", ""]
    m_frames = re.fullmatch(r"frames\s*:\s*(\d+)", head[0], re.IGNORECASE)
    m_time = re.fullmatch(r"frame\s*time\s*:\s*(\d*\.?\d+(?:e[-+]?\d+)?)", head[1], re.IGNORECASE)
    if m_frames is None or m_time is None or float(m_time.group(1)) <= 0:
        raise ClipError(path, f"MOTION: expected 'Frames: N' then 'Frame Time: seconds > 0', got {head[:2]}")
    frame_time = float(m_time.group(1))
    declared, data = int(m_frames.group(1)), after[2:]
    if declared == 0 or not data:
        raise ClipError(path, "no frames")
    if len(data) < declared:
        raise ClipError(path, f"the header declares {declared} frames but the file ends", len(data))
    if len(data) > declared:
        log.warning("%s: %d lines after the %d declared frames ignored", path, len(data) - declared, declared)
    frames = np.empty((declared, ncols))
    for f, i in enumerate(data[:declared]):
        if len(words[i]) != ncols:
            raise ClipError(path, f"expected {ncols} values (the channel count), got {len(words[i])}", f)
        try:
            frames[f] = [float(w) for w in words[i]]
        except ValueError as e:
            raise ClipError(path, f"non-numeric value ({e})", f) from None
    bad = ~np.isfinite(frames).all(axis=1)
    if bad.any():
        raise ClipError(path, "non-finite value (NaN or inf)", int(np.argmax(bad)))
    return joints, frames, frame_time


# Import and retargeting ----------------------------------------------------
def forward_kinematics(joints: list[Joint], frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global rotation matrices [T, J, 3, 3] and positions [T, J, 3] of every joint, in the file's axes."""
    n = frames.shape[0]
    rots, pos = np.zeros((n, len(joints), 3, 3)), np.zeros((n, len(joints), 3))
    for j, jt in enumerate(joints):
        r, t = np.broadcast_to(np.eye(3), (n, 3, 3)), np.tile(jt.offset, (n, 1))
        for c, ch in enumerate(jt.channels):
            axis, values = _AXES[ch[0]], frames[:, jt.column + c]
            if ch.endswith("position"):
                t[:, axis] = values
            else:
                r = r @ axis_rotation(axis, np.deg2rad(values))
        if jt.parent < 0:
            rots[:, j], pos[:, j] = r, t
        else:
            rots[:, j] = rots[:, jt.parent] @ r
            pos[:, j] = pos[:, jt.parent] + (rots[:, jt.parent] @ t[..., None])[..., 0]
    return rots, pos


def rest_positions(joints: list[Joint]) -> np.ndarray:
    """Positions [J, 3] of the joints and End Sites in the rest pose (all channels zero)."""
    out = np.zeros((len(joints), 3))
    for j, jt in enumerate(joints):
        out[j] = jt.offset + (out[jt.parent] if jt.parent >= 0 else 0.0)
    return out


def guess_scale(heights: np.ndarray) -> float:
    """Metres per file unit from the rest pose's vertical extent: metres, centimetres or millimetres."""
    span = float(np.ptp(heights))
    return 1.0 if span <= 10.0 else 0.01 if span <= 400.0 else 0.001


def match_joints(path: Path, joints: list[Joint], bodies: list[str], joint_map: dict | None) -> dict:
    """Our body name -> index of its source joint (the first in hierarchy order that maps to it)."""
    table = {k.lower(): v for k, v in (DEFAULT_JOINT_MAP if joint_map is None else joint_map).items()}
    unknown = sorted(set(table.values()) - set(bodies))
    if unknown:
        raise ClipError(path, f"joint_map targets {unknown} are not bodies of the character {bodies}")
    out: dict[str, int] = {}
    for j, jt in enumerate(joints):
        key = jt.name.lower()
        body = None if jt.end_site else table.get(key, table.get(key.rsplit(":", 1)[-1]))
        if body is not None and body not in out:
            out[body] = j
    return out


def _swing(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation (quaternion) taking direction u to direction v; identity if either is zero."""
    nu, nv = np.linalg.norm(u), np.linalg.norm(v)
    if nu < 1e-9 or nv < 1e-9:
        return _IDENTITY
    u, v = u / nu, v / nv
    if u @ v < -1.0 + 1e-12:  # opposite: half a turn about any perpendicular axis
        axis = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
        return np.concatenate(([0.0], axis / np.linalg.norm(axis)))
    return rot.normalize(np.concatenate(([1.0 + u @ v], np.cross(u, v))))


def rest_corrections(character: Character, joints: list[Joint], rest: np.ndarray, src: dict) -> dict:
    """Body index -> quaternion C with G_ours = G_source C, for every mapped body (see the module doc).

    rest: the source's rest positions [J, 3] in our axes (z-up); src: match_joints's answer.
    """
    names, (parent, kids) = character.body_names, _tree(character)
    body_pos = character.model.body_pos[1:]
    ours = np.zeros_like(body_pos)  # our rest positions (all body_quat are identity)
    for b in range(len(names)):
        ours[b] = body_pos[b] + (ours[parent[b]] if parent[b] >= 0 else 0.0)

    def is_below(j: int, anc: int) -> bool:
        while j >= 0 and j != anc:
            j = joints[j].parent
        return j == anc

    def bones(b: int) -> tuple[np.ndarray, np.ndarray]:
        """Our and the source's rest bone vectors for body b."""
        s = src[names[b]]
        if kids[b]:
            child = src.get(names[kids[b][0]])
            if child is not None and is_below(child, s):
                return body_pos[kids[b][0]], rest[child] - rest[s]
        mine = body_pos[kids[b][0]] if kids[b] else np.asarray(END_SITES.get(names[b], (0.0, 0.0, 0.0)))
        direct = [j for j, jt in enumerate(joints) if jt.parent == s]
        return mine, (rest[direct].mean(axis=0) - rest[s]) if direct else np.zeros(3)

    facing = _IDENTITY  # turns our rest frame (spine up, hips left to right) onto the source's
    if {"left_hip", "right_hip"} <= set(src):
        (up_ours, up_src), lat_src = bones(0), rest[src["left_hip"]] - rest[src["right_hip"]]
        tilt, axis = _swing(up_ours, up_src), up_src / max(np.linalg.norm(up_src), 1e-12)
        lat = rot.rotate(tilt, ours[names.index("left_hip")] - ours[names.index("right_hip")])
        yaw = np.arctan2(np.cross(lat, lat_src) @ axis, lat @ lat_src - (lat @ axis) * (lat_src @ axis))
        facing = rot.mul(rot.from_expmap(yaw * axis), tilt)
    out = {}
    for b in (b for b, name in enumerate(names) if name in src):
        mine, theirs = bones(b)
        out[b] = rot.mul(_swing(rot.rotate(facing, mine), theirs), facing)
    return out


def load(
    character: Character,
    path: str | Path,
    name: str | None = None,
    joint_map: dict[str, str] | None = None,
    scale: float | None = None,
    up: str = "y",
    loop: bool = False,
) -> RawClip:
    """Read a BVH file and retarget it onto our character (see the module doc).

    joint_map: source joint name -> our body name (case-insensitive); replaces DEFAULT_JOINT_MAP.
    scale: metres per file unit; guessed from the skeleton's height when None.
    up: "y" for the usual y-up files (x forward, z right), "z" for files in our axes.
    """
    path = Path(path)
    if up not in ("y", "z"):
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    axes = Y_TO_Z if up == "y" else np.eye(3)
    joints, frames, frame_time = parse(path)
    rest = rest_positions(joints) @ axes.T
    scale = guess_scale(rest[:, 2]) if scale is None else scale
    names, (parent, _) = character.body_names, _tree(character)
    src = match_joints(path, joints, names, joint_map)
    if names[0] not in src:
        raise ClipError(path, f"no source joint maps to our {names[0]} (pass a joint_map)")
    g_mat, g_pos = forward_kinematics(joints, frames)
    g_quat = rot.from_matrix(axes @ g_mat @ axes.T)  # [T, J, 4] in our axes
    corr = rest_corrections(character, joints, rest, src)

    model, n = character.model, frames.shape[0]
    qpos = np.zeros((n, model.nq))
    qpos[:, :3] = g_pos[:, src[names[0]]] @ axes.T * scale
    glob = np.zeros((n, len(names), 4))
    qpos[:, 3:7] = glob[:, 0] = rot.mul(g_quat[:, src[names[0]]], corr[0])
    joint_of_body = {int(b): j for j, b in enumerate(character.body_of_joint)}
    for b in range(1, len(names)):
        j, body, pg = joint_of_body.get(b), names[b], glob[:, parent[b]]
        glob[:, b] = pg
        if j is None:
            continue
        sl = character.joint_qpos[j]
        if body not in src:
            log.warning("%s: no source joint maps to %s; it keeps the identity rotation", path, body)
            qpos[:, sl.start] = 1.0 if character.joint_types[j] == "ball" else 0.0
            continue
        local = rot.mul(rot.conj(pg), rot.mul(g_quat[:, src[body]], corr[b]))
        local = np.where(local[:, :1] < 0, -local, local)
        if character.joint_types[j] == "hinge":  # keep the twist about the axis
            axis = model.jnt_axis[model.joint(character.joint_names[j]).id]
            axis = axis / np.linalg.norm(axis)
            angle = (2.0 * np.arctan2(local[:, 1:] @ axis, local[:, 0]) + np.pi) % (2.0 * np.pi) - np.pi
            qpos[:, sl.start] = angle
            local = rot.from_expmap(angle[:, None] * axis)
        else:
            qpos[:, sl] = local
        glob[:, b] = rot.mul(pg, local)
    return RawClip(name or path.stem, qpos, np.arange(n) * frame_time, loop, source=str(path))
