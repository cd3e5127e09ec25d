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

* Joints are matched to our bodies by the naming conventions of Mixamo, CMU, LaFAN1,
  the mocap-bank/Biovision Collar-Shoulder-Elbow-Wrist and Hip-Knee-Ankle skeletons,
  3ds Max bipeds, Blender and Rigify (metarig and DEF- bones) and game rigs
  (`bvh_names`), then by the skeleton where the names are ambiguous ("LeftShoulder" is
  the clavicle in Mixamo, the upper arm under a "LeftCollar"). `joint_map` (source
  joint name -> our body) is applied first and overrides the conventions for the
  bodies it names. Our root and every body driven by a joint must find a source joint
  (else one ClipError listing them), except the neck (a warning; it keeps the identity
  rotation).
* Per body, G_ours = G_source C: the source joint's global orientation and a
  rest-pose correction C, the facing alignment F (our rest frame, spine up and hips
  left to right, onto the source's) then the smallest rotation taking our rest
  bone, turned by F, onto the source's. A bone goes to the first child (for the
  source: the joint matched to it, across unmatched joints and past a zero-length
  one such as CMU's Neck on Spine1), to the mean of the children where that child
  has no source (for both skeletons), or, for our leaves, to the End Site (for the
  source: the mean of its children's offsets). Files from `save` import with
  identity corrections. Hinges keep the twist about their axis.
* A bone's direction leaves its twist open, and a rest pose far from ours (LaFAN1's,
  every bone along its joint's x axis: the legs along the spine) guesses it wrong
  (knees bending forward, feet upside down). The limbs' twists are read from the
  motion instead: the planes of thigh and shin, upper arm and forearm, shin and foot
  over the clip (`bvh_retarget.limb_twists`).
* A first frame apart from the motion (a joint turning by over 45 degrees to the next
  frame, and four times as far as the clip's frames do at the 95th percentile; the
  cgspeed CMU conversion starts each file with its rest pose) is dropped.
* The root position is the matched source joint's (metres, z-up), horizontally as is.
  Vertically the clip is put on the ground (`ground`, default on): shifted so that the
  5th percentile over the frames of the character's lowest point (in practice a foot)
  is at the height where the bundled walks have it (`bvh_retarget.GROUND_HEIGHT`, 0 m;
  they sit at -0.4 to +0.3 cm). Our legs are rarely the source's length (the
  reference model's are 0.88 m, hip to sole), so without it the feet float or sink by
  the difference over the whole clip. `ground=None` keeps the file's heights.

`scale` (metres per file unit) defaults to a guess from the legs' bone lengths (hip to
knee to ankle, whatever the rest pose's orientation): the unit of UNITS (metres,
centimetres, millimetres, inches, CMU's 1/0.45 inch) that makes them closest to a
person's 0.85 m; a leg that is no human leg in any of them is a ClipError naming the
file. Other sizes or units need an explicit `scale`.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from workers.body import rotations as rot
from workers.body.character import Character
from workers.motion.clip import RawClip, interpolate_qpos, normalize_quats
from workers.motion.errors import ClipError
from workers.motion.formats.bvh_names import match_joints, refuse_unmatched, unmatched
from workers.motion.formats.bvh_retarget import END_SITES, GROUND_HEIGHT, ground_shift, rest_corrections, tree
from workers.motion.formats.deepmimic import Y_TO_Z

log = logging.getLogger(__name__)
# The frame times a BVH file may declare: 1 to 10,000 frames a second (mocap runs at 30-480).
FRAME_TIME_MIN, FRAME_TIME_MAX = 1e-4, 1.0

SAVE_UNITS_PER_METRE = 100.0  # `save` writes centimetres
SAVE_ROTATION_ORDER = "ZXY"
# Units a file may be in (metres per unit), the leg (hip to knee to ankle) guess_scale expects of a
# person (ours 0.83 m, LaFAN1's 0.86, CMU 01_14's 0.84) and the legs it accepts (a child's to a tall
# adult's, with room for the 1.6x between centimetres and inches).
UNITS = {"metres": 1.0, "centimetres": 0.01, "millimetres": 0.001, "inches": 0.0254, "CMU units": 0.0254 / 0.45}
PERSON_LEG = 0.85
LEG_RANGE = (0.4, 1.4)
# A first frame from which some joint turns by more than this (radians) to the next, and by four
# times the 95th percentile of the clip's largest turn a frame, is a pose put before the motion
# (the cgspeed CMU conversion starts each file with its rest pose).
REST_FRAME_JUMP = np.deg2rad(45.0)
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
    parent, kids = tree(character)
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
    filled = [i for i, line in enumerate(lines) if line.strip()]  # words split a line at a time (long clips)
    if not filled or lines[filled[0]].split()[0].upper() != "HIERARCHY":
        raise ClipError(path, "no HIERARCHY section (not a BVH file)")
    motion = next((i for i in filled if lines[i].split(None, 1)[0].upper() == "MOTION"), None)
    if motion is None:
        raise ClipError(path, "no MOTION section")
    joints, ncols = _parse_hierarchy(path, [t for line in lines[filled[0] : motion] for t in line.split()][1:])
    after = [i for i in filled if i > motion]
    head = [" ".join(lines[i].split()) for i in after[:2]] + ["", ""]
    m_frames = re.fullmatch(r"frames\s*:\s*(\d+)", head[0], re.IGNORECASE)
    m_time = re.fullmatch(r"frame\s*time\s*:\s*(\d*\.?\d+(?:e[-+]?\d+)?)", head[1], re.IGNORECASE)
    if m_frames is None or m_time is None or float(m_time.group(1)) <= 0:
        raise ClipError(path, f"MOTION: expected 'Frames: N' then 'Frame Time: seconds > 0', got {head[:2]}")
    frame_time = float(m_time.group(1))
    declared, data = int(m_frames.group(1)), after[2:]
    if not FRAME_TIME_MIN <= frame_time <= FRAME_TIME_MAX:  # resampled, its frames would fill the memory
        raise ClipError(
            path,
            f"Frame Time {frame_time:g} s makes its {declared} frames last {declared * frame_time:g} s; motion capture "
            f"runs at {1 / FRAME_TIME_MAX:g} to {1 / FRAME_TIME_MIN:g} frames a second (Frame Time {FRAME_TIME_MIN:g} "
            f"to {FRAME_TIME_MAX:g} s)",
        )
    if declared == 0 or not data:
        raise ClipError(path, "no frames")
    if len(data) < declared:
        raise ClipError(path, f"the header declares {declared} frames but the file ends", len(data))
    if len(data) > declared:
        log.warning("%s: %d lines after the %d declared frames ignored", path, len(data) - declared, declared)
    frames = np.empty((declared, ncols))
    for f, i in enumerate(data[:declared]):
        words = lines[i].split()
        if len(words) != ncols:
            raise ClipError(path, f"expected {ncols} values (the channel count), got {len(words)}", f)
        try:
            frames[f] = [float(w) for w in words]
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


def leg_length(rest: np.ndarray, src: dict) -> float | None:
    """Hip to knee to ankle (file units) of the source's rest pose, mean over the sides; None without a leg."""
    legs = [
        np.linalg.norm(rest[src[f"{s}_knee"]] - rest[src[f"{s}_hip"]])
        + np.linalg.norm(rest[src[f"{s}_ankle"]] - rest[src[f"{s}_knee"]])
        for s in ("left", "right")
        if {f"{s}_hip", f"{s}_knee", f"{s}_ankle"} <= set(src)
    ]
    return float(np.mean(legs)) if legs else None


def guess_scale(path: Path, leg: float) -> float:
    """Metres per file unit: the UNITS entry that makes a leg (hip to ankle) closest to a person's PERSON_LEG.

    Bone lengths do not depend on how the rest pose stands (upright, T-pose, or LaFAN1's, every bone
    along its joint's x axis). A leg outside LEG_RANGE in every unit is a ClipError naming the file.
    """
    best = min(UNITS, key=lambda unit: abs(np.log(max(leg, 1e-12) * UNITS[unit] / PERSON_LEG)))
    if not LEG_RANGE[0] <= leg * UNITS[best] <= LEG_RANGE[1]:
        raise ClipError(
            path,
            f"cannot tell the file's unit: its legs (hip to knee to ankle) are {leg:.4g} units long, a human "
            f"leg ({LEG_RANGE[0]}-{LEG_RANGE[1]} m) in none of {', '.join(UNITS)}; convert it to one of "
            "them (or call workers.motion.formats.bvh.load with scale=, metres per unit)",
        )
    return UNITS[best]


def _starts_with_rest_frame(g_mat: np.ndarray) -> bool:
    """Whether frame 0 of global rotations [T, J, 3, 3] is a pose apart from the motion (REST_FRAME_JUMP)."""
    if len(g_mat) < 3:
        return False
    cos = (np.einsum("tjab,tjab->tj", g_mat[:-1], g_mat[1:]) - 1.0) / 2.0  # trace(R_t^T R_t+1) = 1 + 2 cos
    turn = np.arccos(np.clip(cos, -1.0, 1.0)).max(axis=1)  # [T - 1] largest turn of a joint
    return bool(turn[0] > REST_FRAME_JUMP and turn[0] > 4.0 * np.percentile(turn[1:], 95))


def load(
    character: Character,
    path: str | Path,
    name: str | None = None,
    joint_map: dict[str, str] | None = None,
    scale: float | None = None,
    up: str = "y",
    loop: bool = False,
    ground: float | None = GROUND_HEIGHT,
) -> RawClip:
    """Read a BVH file and retarget it onto our character (see the module doc).

    joint_map: source joint name -> our body name (case-insensitive), added to (and overriding)
      the naming conventions of `bvh_names`.
    scale: metres per file unit; guessed from the legs' bone lengths when None (guess_scale).
    up: "y" for the usual y-up files (x forward, z right), "z" for files in our axes.
    ground: the height (m) for the clip's ground contact (see the module doc); None keeps the file's.
    """
    path = Path(path)
    if up not in ("y", "z"):
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    axes = Y_TO_Z if up == "y" else np.eye(3)
    joints, frames, frame_time = parse(path)
    g_mat, g_pos = forward_kinematics(joints, frames)
    if _starts_with_rest_frame(g_mat):
        log.info("%s: frame 0 is a pose put before the motion (as in the cgspeed CMU files); dropped", path)
        frames, g_mat, g_pos = frames[1:], g_mat[1:], g_pos[1:]
    rest = rest_positions(joints) @ axes.T
    names, (parent, _) = character.body_names, tree(character)
    src = match_joints(path, joints, names, joint_map)
    if names[0] not in src:
        raise ClipError(path, f"no source joint maps to our {names[0]} (name it with motion.joint_map)")
    driven = [names[b] for b in sorted({int(b) for b in character.body_of_joint})]
    essential, minor = unmatched(driven, src)
    if essential:
        refuse_unmatched(path, joints, essential)
    for body in minor:
        log.warning("%s: no source joint maps to %s; it keeps the identity rotation", path, body)
    if scale is None:
        leg = leg_length(rest, src)
        scale = guess_scale(path, leg) if leg is not None else UNITS["metres"]
        unit = next(k for k, v in UNITS.items() if v == scale)
        log.info("%s: read in %s (legs %.4g units; pass scale= otherwise)", path, unit, leg or 0.0)
    g_rot = {j: axes @ g_mat[:, j] @ axes.T for j in sorted(set(src.values()))}  # the mapped joints', our axes
    del g_mat
    g_quat = {j: rot.from_matrix(m) for j, m in g_rot.items()}  # [T, 4] each
    corr = rest_corrections(character, joints, rest, src, (g_rot, g_pos @ axes.T))
    del g_rot

    model, n = character.model, frames.shape[0]
    qpos = np.zeros((n, model.nq))
    qpos[:, :3] = g_pos[:, src[names[0]]] @ axes.T * scale
    glob = np.zeros((n, len(names), 4))
    qpos[:, 3:7] = glob[:, 0] = rot.mul(g_quat[src[names[0]]], corr[0])
    joint_of_body = {int(b): j for j, b in enumerate(character.body_of_joint)}
    for b in range(1, len(names)):
        j, body, pg = joint_of_body.get(b), names[b], glob[:, parent[b]]
        glob[:, b] = pg
        if j is None:
            continue
        sl = character.joint_qpos[j]
        if body not in src:  # a minor body (warned above)
            qpos[:, sl.start] = 1.0 if character.joint_types[j] == "ball" else 0.0
            continue
        local = rot.mul(rot.conj(pg), rot.mul(g_quat[src[body]], corr[b]))
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
    if ground is not None and character.root_dofs:
        shift = ground_shift(character, qpos, ground)
        log.info("%s: put on the ground, root moved %+.1f cm", path, 100 * shift)
        qpos[:, 2] += shift
    return RawClip(name or path.stem, qpos, np.arange(n) * frame_time, loop, source=str(path))


__all__ = [
    "END_SITES", "UNITS", "Joint", "euler_to_matrix", "forward_kinematics", "guess_scale", "leg_length", "load",
    "match_joints", "matrix_to_euler", "parse", "rest_corrections", "rest_positions", "save",
]  # fmt: skip
