"""BVH export and import with retargeting (workers.motion.formats.bvh)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import mujoco
import numpy as np
import pytest

from workers.body import rotations as rot
from workers.body.character import Character
from workers.motion.clip import RawClip, interpolate_qpos, normalize_quats, process, transform_qpos
from workers.motion.errors import ClipError
from workers.motion.formats import bvh, load_raw
from workers.motion.formats.bvh_retarget import GROUND_PERCENTILE, lowest_points
from workers.motion.formats.deepmimic import Y_TO_Z

LAFAN_NAMES = {
    "root": "Hips", "chest": "Spine", "neck": "Neck",
    "right_shoulder": "RightArm", "right_elbow": "RightForeArm", "right_wrist": "RightHand",
    "left_shoulder": "LeftArm", "left_elbow": "LeftForeArm", "left_wrist": "LeftHand",
    "right_hip": "RightUpLeg", "right_knee": "RightLeg", "right_ankle": "RightFoot",
    "left_hip": "LeftUpLeg", "left_knee": "LeftLeg", "left_ankle": "LeftFoot",
}  # fmt: skip


@pytest.fixture(scope="module")
def character() -> Character:
    return Character.load()


@pytest.fixture(scope="module")
def walk(character):
    return load_raw(character, "humanoid3d_walk")


@pytest.fixture(scope="module")
def walk_globals(character, walk):
    return body_globals(character, normalize_quats(character, walk.qpos))


def body_globals(character: Character, qpos: np.ndarray) -> np.ndarray:
    """Global body rotations [T, B, 4] by MuJoCo's forward kinematics."""
    data = mujoco.MjData(character.model)
    out = np.zeros((qpos.shape[0], character.num_bodies, 4))
    for t, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(character.model, data)
        out[t] = data.xquat[1:]
    return out


def assert_same_poses(character, expected, actual, rot_tol=1e-4, pos_tol=1e-5):
    expected = normalize_quats(character, expected)
    np.testing.assert_allclose(actual[:, :3], expected[:, :3], atol=pos_tol)
    quats = np.concatenate(([np.arange(3, 7)], character.ball_qpos))
    err = rot.angle(rot.mul(rot.conj(expected[:, quats]), rot.normalize(actual[:, quats])))
    assert err.max() < rot_tol, f"rotation error {err.max():.3g} rad"
    hinges = character.hinge_qpos
    np.testing.assert_allclose(actual[:, hinges], expected[:, hinges], atol=rot_tol)


def our_skeleton(character, names=None, rotations="Zrotation Xrotation Yrotation"):
    """Our skeleton as a list of [name, parent, offset (z-up, m), channels, End Site offset or None]."""
    names = names or {}
    parent = character.model.body_parentid[1:] - 1
    skel = []
    for b, body in enumerate(character.body_names):
        channels = ("Xposition Yposition Zposition " if b == 0 else "") + rotations
        end = bvh.END_SITES.get(body) if b not in parent[1:] else None
        offset = np.zeros(3) if b == 0 else character.model.body_pos[b + 1].copy()
        skel.append([names.get(body, body), int(parent[b]) if b else -1, offset, channels.split(), end])
    return skel


def write_bvh(path, skel, glob, root_pos, frame_time, scale=1.0, y_up=True, newline="\n"):
    """A BVH of skeleton `skel` whose joints have the global rotations glob [T, J, 4] (z-up).

    The hierarchy is written with uneven whitespace; skel must list parents before children.
    """
    axes = Y_TO_Z if y_up else np.eye(3)  # file -> z-up
    dfs = []  # the channels' order is the hierarchy's

    def vec(v):
        return "  ".join(f"{x:.12g}" for x in axes.T @ np.asarray(v) * scale)

    def block(j, pad):
        name, parent, offset, channels, end = skel[j]
        dfs.append(j)
        out = [f"{pad}{'ROOT' if parent < 0 else 'JOINT'}\t{name} {{", f"{pad}\tOFFSET {vec(offset)} "]
        out.append(f"{pad}\tCHANNELS  {len(channels)} " + " ".join(channels))
        for c in (c for c in range(len(skel)) if skel[c][1] == j):
            out += block(c, pad + "\t")
        if end is not None:
            out += [f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {vec(end)}", f"{pad}\t}}"]
        return out + [pad + "}"]

    text = ["HIERARCHY", *block(0, "")]
    pos, cols = root_pos @ axes * scale, []
    for j in dfs:
        _, parent, _, channels, _ = skel[j]
        local = glob[:, j] if parent < 0 else rot.mul(rot.conj(glob[:, parent]), glob[:, j])
        local = np.concatenate((local[:, :1], local[:, 1:] @ axes), axis=-1)
        order = "".join(c[0] for c in channels if c.endswith("rotation"))
        angles = bvh.matrix_to_euler(rot.to_matrix(local), order)
        for c in channels:
            cols.append(pos[:, "XYZ".index(c[0])] if c.endswith("position") else angles[:, order.index(c[0])])
    data = np.stack(cols, axis=1)
    lines = [*text, "MOTION", f"Frames:\t{len(data)}", f"Frame Time: {float(frame_time)!r}"]
    lines += ["  ".join(f"{x:.12g}" for x in row) + " " for row in data]
    path.write_bytes((newline.join(lines) + newline).encode())


# ----------------------------------------------------------------------------
# Euler angles
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("order", ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])
def test_euler_angles_follow_bvh_convention(order):
    rng = np.random.default_rng(0)
    angles = rng.uniform(-180, 180, (64, 3))
    angles[:4, 1] = [90, -90, 89.9999, -90]  # gimbal lock
    elementary = {
        "X": lambda c, s: [[1, 0, 0], [0, c, -s], [0, s, c]],
        "Y": lambda c, s: [[c, 0, s], [0, 1, 0], [-s, 0, c]],
        "Z": lambda c, s: [[c, -s, 0], [s, c, 0], [0, 0, 1]],
    }
    expected = np.zeros((len(angles), 3, 3))
    for t, row in enumerate(np.deg2rad(angles)):
        m = np.eye(3)
        for axis, a in zip(order, row, strict=True):
            m = m @ np.array(elementary[axis](np.cos(a), np.sin(a)))
        expected[t] = m
    np.testing.assert_allclose(bvh.euler_to_matrix(angles, order), expected, atol=1e-12)
    back = bvh.matrix_to_euler(expected, order)
    assert np.all(np.abs(back[:, 1]) <= 90 + 1e-9)
    np.testing.assert_allclose(bvh.euler_to_matrix(back, order), expected, atol=1e-9)


# ----------------------------------------------------------------------------
# Round trips through our own skeleton
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("clip", ["humanoid3d_walk", "humanoid3d_run"])
def test_save_then_load_gives_the_same_clip(character, tmp_path, clip):
    raw = load_raw(character, clip)
    path = tmp_path / f"{clip}.bvh"
    bvh.save(character, raw, path)
    text = path.read_text()
    assert text.startswith("HIERARCHY\nROOT root\n") and "JOINT left_ankle" in text and "End Site" in text
    back = load_raw(character, path)  # dispatches on the suffix
    assert back.name == clip and back.source == str(path) and not back.loop
    # Put on the ground: moved up by what the clip's 5th percentile of its lowest point lies below 0
    # (walk: 0.40 cm, run: 5.9 cm; the bundled run sinks into the floor).
    lift = -np.percentile(lowest_points(character, normalize_quats(character, raw.qpos)), GROUND_PERCENTILE)
    assert 0.003 < lift < 0.07
    expected = raw.qpos.copy()
    expected[:, 2] += lift
    assert_same_poses(character, expected, back.qpos)
    assert_same_poses(character, raw.qpos, bvh.load(character, path, ground=None).qpos)
    np.testing.assert_allclose(back.times, raw.times, rtol=0, atol=1e-9)


def test_round_trip_body_positions_agree(character, walk, tmp_path):
    path = tmp_path / "walk.bvh"
    bvh.save(character, walk, path)
    back = bvh.load(character, path, loop=True, ground=None)
    assert back.loop
    a, b = process(character, walk, 30), process(character, back, 30)
    assert a.xpos.shape == b.xpos.shape
    np.testing.assert_allclose(b.xpos, a.xpos, atol=1e-4)


def test_scale_and_resampling(character, walk, tmp_path):
    path = tmp_path / "walk.bvh"
    bvh.save(character, walk, path, fps=60)
    guessed = bvh.load(character, path, ground=None)
    explicit = bvh.load(character, path, scale=0.01, ground=None)
    assert len(guessed.times) == int(np.floor(walk.duration * 60 + 1e-6)) + 1
    np.testing.assert_allclose(np.diff(guessed.times), 1 / 60)
    np.testing.assert_allclose(guessed.qpos, explicit.qpos)
    assert_same_poses(character, interpolate_qpos(character, walk, guessed.times), guessed.qpos)
    as_metres = bvh.load(character, path, scale=1.0, ground=None)
    np.testing.assert_allclose(as_metres.qpos[:, :3], 100 * guessed.qpos[:, :3])


def _renamed(text: str, old: str, new: str) -> str:
    return text.replace(f"JOINT {old}\n", f"JOINT {new}\n").replace(f"ROOT {old}\n", f"ROOT {new}\n")


def test_unmatched_joint_is_refused_and_joint_map_extends_the_conventions(character, walk, tmp_path):
    """A knee without a source is one ClipError naming the file and body; a joint_map entry fixes it."""
    good = tmp_path / "walk.bvh"
    bvh.save(character, walk, good)
    path = tmp_path / "renamed.bvh"
    path.write_text(_renamed(good.read_text(), "left_knee", "Segment7"))
    with pytest.raises(ClipError) as info:
        bvh.load(character, path)
    text = str(info.value)
    assert "renamed.bvh" in text and "left_knee" in text and "joint_map" in text and "Segment7" in text
    assert "right_knee" not in text.split("The file's joints")[0]
    # The map adds to the conventions: only the renamed joint is named, the others still match.
    back = bvh.load(character, path, joint_map={"segment7": "left_knee"}, ground=None)
    assert_same_poses(character, walk.qpos, back.qpos)
    # User entries win over the conventions, and their joints serve no other body.
    joints = bvh.parse(good)[0]
    swap = {"right_knee": "left_knee", "LEFT_KNEE": "right_knee"}
    src = {b: joints[j].name for b, j in bvh.match_joints(good, joints, character.body_names, swap).items()}
    assert src["left_knee"] == "right_knee" and src["right_knee"] == "left_knee" and src["left_hip"] == "left_hip"
    src = bvh.match_joints(good, joints, character.body_names, {"chest": "neck"})
    assert joints[src["neck"]].name == "chest" and "chest" not in src  # our chest: no spine joint left


def test_a_missing_neck_only_warns(character, walk, tmp_path, caplog):
    good = tmp_path / "walk.bvh"
    bvh.save(character, walk, good)
    path = tmp_path / "no_neck.bvh"
    path.write_text(_renamed(good.read_text(), "neck", "Segment9"))
    with caplog.at_level(logging.WARNING, logger=bvh.__name__):
        back = bvh.load(character, path, ground=None)
    assert "neck" in caplog.text and "identity" in caplog.text
    neck = character.joint_qpos[character.joint_names.index("neck")]
    np.testing.assert_array_equal(back.qpos[:, neck], np.tile([1.0, 0.0, 0.0, 0.0], (len(back.qpos), 1)))
    expected = walk.qpos.copy()
    expected[:, neck] = [1.0, 0.0, 0.0, 0.0]
    assert_same_poses(character, expected, back.qpos)


def test_grounding_ignores_the_files_height(character, walk, tmp_path):
    """The same motion 20 cm higher or lower in the file imports to the same heights."""
    path = tmp_path / "walk.bvh"
    bvh.save(character, walk, path)
    base = bvh.load(character, path)
    low = lowest_points(character, base.qpos)
    assert abs(np.percentile(low, GROUND_PERCENTILE)) < 1e-9  # at GROUND_HEIGHT, 0 m
    for dz in (0.2, -0.2):
        moved = walk.qpos.copy()
        moved[:, 2] += dz
        bvh.save(character, RawClip(walk.name, moved, walk.times, False), path)
        np.testing.assert_allclose(bvh.load(character, path).qpos, base.qpos, atol=1e-6)
        np.testing.assert_allclose(bvh.load(character, path, ground=None).qpos[:, 2], moved[:, 2], atol=1e-6)
    assert bvh.load(character, path, ground=0.05).qpos[:, 2] == pytest.approx(base.qpos[:, 2] + 0.05, abs=1e-9)


def test_a_rest_frame_before_the_motion_is_dropped(character, walk, tmp_path, caplog):
    """As the cgspeed CMU files: frame 0 is the skeleton's rest pose (all rotations zero), here facing
    a quarter turn away from the walk that follows."""
    turned = RawClip(walk.name, transform_qpos(walk.qpos, np.pi / 2, np.zeros(3)), walk.times, False)
    path = tmp_path / "walk.bvh"
    bvh.save(character, turned, path)
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("Frame Time")) + 1
    values = lines[first].split()
    rest = values[:3] + ["0"] * (len(values) - 3)
    lines[first - 2] = f"Frames: {len(lines) - first + 1}"
    path.write_text("\n".join([*lines[:first], " ".join(rest), *lines[first:]]) + "\n")
    with caplog.at_level(logging.INFO, logger=bvh.__name__):
        back = bvh.load(character, path, ground=None)
    assert "frame 0" in caplog.text
    assert_same_poses(character, turned.qpos, back.qpos)
    # A clip that starts from rest and moves on smoothly keeps its first frame.
    assert not bvh._starts_with_rest_frame(np.broadcast_to(np.eye(3), (40, 3, 3, 3)).copy())


@pytest.mark.parametrize(
    ("leg", "unit"),
    [
        (0.831, "metres"),  # ours: 0.4215 + 0.4099
        (0.654, "metres"),  # bvhtools' Rigify-named test3.bvh (a small character)
        (82.7, "centimetres"),  # bvhtoolbox's Mixamo export
        (85.87, "centimetres"),  # LaFAN1: 43.50 + 42.37, its rest pose lying along x
        (870.0, "millimetres"),
        (33.5, "inches"),  # 0.85 m
        (14.9, "CMU units"),  # cgspeed's CMU skeleton: 7.6 + 7.3 (0.84 m)
    ],
)
def test_guess_scale_reads_the_unit_from_the_legs(leg, unit):
    assert bvh.guess_scale(Path("x.bvh"), leg) == bvh.UNITS[unit]


@pytest.mark.parametrize("leg", [3.0, 300.0])
def test_a_leg_human_in_no_unit_is_one_line_naming_the_file(leg):
    """3 units: 3 m, 7.6 cm in inches, 17 cm in CMU units; 300: 3 m in centimetres, 7.6 m in inches."""
    with pytest.raises(ClipError, match=r"x\.bvh.*cannot tell the file's unit.*scale=") as e:
        bvh.guess_scale(Path("x.bvh"), leg)
    assert "\n" not in str(e.value)


def test_unit_from_the_legs_whatever_the_rest_pose(character, walk, tmp_path):
    """Our skeleton with every bone laid along x (LaFAN1's rest pose) is read in centimetres all the
    same: its rest height (a few cm) once read it in metres, putting the root 100 m off at 100 m."""
    skel = our_skeleton(character)
    for row in skel[1:]:
        row[2] = np.array([np.linalg.norm(row[2]), 0.0, 0.0])  # each bone along its parent's x
    joints = [bvh.Joint(name, parent, offset) for name, parent, offset, *_ in skel]
    rest = bvh.rest_positions(joints)
    assert np.ptp(rest[:, 2]) == 0.0  # flat: no height to read a unit from
    src = {name: j for j, (name, *_) in enumerate(skel)}
    assert bvh.guess_scale(Path("x.bvh"), 100.0 * bvh.leg_length(rest, src)) == bvh.UNITS["centimetres"]


# ----------------------------------------------------------------------------
# Files from other skeletons
# ----------------------------------------------------------------------------
def test_renamed_skeleton_other_channel_order_in_centimetres(character, walk, walk_globals, tmp_path):
    """LaFAN1-style names, extra unmapped joints, ZXY root positions and YXZ/XZY rotations, cm, CRLF."""
    skel = our_skeleton(character, LAFAN_NAMES, "Yrotation Xrotation Zrotation")
    skel[0][2] = walk.qpos[0, :3]  # a root OFFSET, which position channels override
    skel[0][3] = "Zposition Xposition Yposition Yrotation Xrotation Zrotation".split()
    glob = walk_globals.copy()
    # Spine1 between Spine and Neck, with a rotation of its own; Neck's local rotation makes up for it.
    neck = character.body_names.index("neck")
    half = skel[neck][2] / 2
    skel.append(["Spine1", 1, half, "Xrotation Zrotation Yrotation".split(), None])
    skel[neck][1:3] = [len(skel) - 1, half]
    twist = rot.from_expmap(np.array([0.3, -0.2, 0.5]))
    extra = [rot.mul(glob[:, 1], twist)]
    # Head under Neck, also a default name for our neck: Neck comes first, so Head's rotation is ignored.
    skel.append(["Head", neck, np.array(bvh.END_SITES["neck"]), skel[neck][3], (0.0, 0.0, 0.1)])
    skel[neck][4] = None
    extra.append(rot.mul(twist, glob[:, neck]))
    limbs = [b for b in range(3, character.num_bodies) if b != neck]
    order = [0, 1, len(skel) - 2, neck, len(skel) - 1, *limbs]
    remap = {old: new for new, old in enumerate(order)}
    skel = [[s[0], remap.get(s[1], -1), *s[2:]] for s in (skel[i] for i in order)]
    glob = np.concatenate((glob, np.stack(extra, axis=1)), axis=1)[:, order]
    path = tmp_path / "lafan_style.bvh"
    write_bvh(path, skel, glob, walk.qpos[:, :3], walk.times[1], scale=100.0, newline="\r\n")
    back = bvh.load(character, path, ground=None)
    assert_same_poses(character, walk.qpos, back.qpos)
    np.testing.assert_allclose(back.times, walk.times, rtol=0, atol=1e-9)


@pytest.mark.parametrize(("y_up", "yaw"), [(True, -np.pi / 2), (False, np.pi)])
def test_source_facing_another_way(character, walk, walk_globals, tmp_path, y_up, yaw):
    """A source whose rest pose faces -y or -x: the facing correction undoes the turn."""
    turn = rot.from_expmap(np.array([0.0, 0.0, yaw]))
    skel = our_skeleton(character)
    for s in skel:
        s[2] = rot.rotate(turn, s[2])
        s[4] = None if s[4] is None else rot.rotate(turn, np.asarray(s[4]))
    glob = rot.mul(walk_globals, rot.conj(turn))
    path = tmp_path / "turned.bvh"
    write_bvh(path, skel, glob, walk.qpos[:, :3], walk.times[1], y_up=y_up)
    back = bvh.load(character, path, up="y" if y_up else "z", ground=None)
    assert_same_poses(character, walk.qpos, back.qpos)


def test_t_pose_source_is_retargeted(character, walk, walk_globals, tmp_path):
    """Arms horizontal at rest: our arm pose is the source's composed with a quarter turn about x."""
    skel = our_skeleton(character)
    glob = walk_globals.copy()
    for side, sign in (("left", 1.0), ("right", -1.0)):
        # C takes our rest arm (down, -z) to the source's (sideways, +-y): a quarter turn about x.
        corr = rot.from_expmap(np.array([sign * np.pi / 2, 0.0, 0.0]))
        for body in ("shoulder", "elbow", "wrist"):
            b = character.body_names.index(f"{side}_{body}")
            length = np.linalg.norm(skel[b][2]) if body != "shoulder" else None
            if length is not None:
                skel[b][2] = np.array([0.0, sign * length, 0.0])
            if skel[b][4] is not None:
                skel[b][4] = (0.0, sign * np.linalg.norm(skel[b][4]), 0.0)
            glob[:, b] = rot.mul(walk_globals[:, b], rot.conj(corr))
    path = tmp_path / "t_pose.bvh"
    write_bvh(path, skel, glob, walk.qpos[:, :3], walk.times[1])
    back = bvh.load(character, path, ground=None)
    assert_same_poses(character, walk.qpos, back.qpos, rot_tol=1e-3)


# ----------------------------------------------------------------------------
# Bad files
# ----------------------------------------------------------------------------
def _edit_frame(frame, edit):
    def apply(text):
        lines = text.splitlines()
        first = next(i for i, line in enumerate(lines) if line.startswith("Frame Time")) + 1
        lines[first + frame] = edit(lines[first + frame].split())
        return "\n".join(lines) + "\n"

    return apply


BAD_FILES = {
    "no_hierarchy": (lambda t: t.replace("HIERARCHY\n", ""), "no HIERARCHY", None),
    "no_motion": (lambda t: t[: t.index("MOTION")], "no MOTION", None),
    "short_frame": (_edit_frame(3, lambda v: " ".join(v[:-1])), "channel count", 3),
    "long_frame": (_edit_frame(0, lambda v: " ".join(v + ["1"])), "channel count", 0),
    "non_numeric": (_edit_frame(2, lambda v: " ".join(["abc"] + v[1:])), "non-numeric", 2),
    "nan": (_edit_frame(5, lambda v: " ".join(v[:4] + ["nan"] + v[5:])), "non-finite", 5),
    "zero_frames": (lambda t: t[: t.index("Frames:")] + "Frames: 0\nFrame Time: 0.1\n", "no frames", None),
    "truncated": (lambda t: "\n".join(t.splitlines()[:-2]) + "\n", "declares", 37),
    "bad_channel": (lambda t: t.replace("Zrotation", "Wrotation", 1), "CHANNELS", None),
    "bad_offset": (lambda t: t.replace("OFFSET 0 0 0", "OFFSET 0 zero 0", 1), "OFFSET", None),
    "unclosed": (lambda t: t.replace("}\nMOTION", "MOTION"), "not closed", None),
    "bad_frame_time": (lambda t: t.replace("Frame Time:", "Frame Time: 0 #"), "Frame Time", None),
    # A frame time of hours: the clip resampled at 30 Hz would be billions of frames (a traceback, or no memory).
    "absurd_frame_time": (
        lambda t: re.sub(r"Frame Time: \S+", "Frame Time: 3600", t),
        "Frame Time 3600 s makes its 39 frames last 140400 s; motion capture runs at 1 to 10000 frames a second",
        None,
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_file_names_file_and_frame(character, walk, tmp_path, case):
    edit, message, frame = BAD_FILES[case]
    good = tmp_path / "good.bvh"
    bvh.save(character, walk, good)
    path = tmp_path / f"{case}.bvh"
    path.write_text(edit(good.read_text()))
    with pytest.raises(ClipError) as info:
        bvh.load(character, path)
    text = str(info.value)
    assert path.name in text and message in text, text
    assert info.value.frame == frame
    if frame is not None:
        assert f"frame {frame}" in text


def test_missing_root_mapping_and_unknown_target(character, walk, tmp_path):
    good = tmp_path / "walk.bvh"
    bvh.save(character, walk, good)
    path = tmp_path / "no_root.bvh"
    path.write_text(_renamed(good.read_text(), "root", "Base"))
    with pytest.raises(ClipError, match="no_root.bvh.*root"):
        bvh.load(character, path)
    assert_same_poses(character, walk.qpos, bvh.load(character, path, joint_map={"Base": "root"}, ground=None).qpos)
    with pytest.raises(ClipError, match="walk.bvh.*pelvis"):
        bvh.load(character, good, joint_map={"root": "pelvis"})
    with pytest.raises(ClipError, match="nowhere.bvh"):
        bvh.load(character, tmp_path / "nowhere.bvh")
