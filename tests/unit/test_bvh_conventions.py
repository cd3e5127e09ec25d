"""Mocap in the conventions labs train on: LaFAN1, CMU and Rigify files import on the ground, every joint matched.

* LaFAN1 (the data set of ProtoMotions, mjlab and LocoMuJoCo): `testBvhFiles/test.bvh` of the
  `bvhtools` 1.6.0 sdist on PyPI (MIT; the package redistributes a LaFAN1 clip of Ubisoft La
  Forge's, whose own licence is CC BY-NC-ND 4.0), 7184 frames at 30 Hz: four minutes, in
  centimetres, every bone along its joint's x axis in the rest pose (so the rest pose is a few
  centimetres tall: a unit read from its height was metres, and the checker refused the clip at
  frame 340 with the root 100 m from its start), legs and feet turned by half a turn from ours.
* Rigify: `testBvhFiles/test3.bvh` of the same sdist, metarig names (pelvis, spine, spine.001,
  neck, shoulder.L, upper_arm.L, forearm.L, thigh.L, shin.L, foot.L), metres, position channels on
  every joint as Blender writes them, 3089 frames at 24 Hz (two minutes).
* CMU: no CMU file is reachable from PyPI, npm or Debian's packages (searched: bvhtools,
  bvhtoolbox, bvhio, bvhsdk, pybvh, pybvh-ml, bvhtodeepmimic, humex-converter-lafan, three's
  npm tarball; `apt-cache search bvh|mocap`), so `cmu_walk` writes one here in the cgspeed
  conversion's convention: its names (LHipJoint, LeftUpLeg, LeftLeg, LeftFoot, LeftToeBase,
  LowerBack, Spine, Spine1, a zero-length Neck, Neck1, Head, LeftShoulder, LeftArm, LeftForeArm,
  LeftHand, LeftFingerBase, LThumb), CMU units (1/0.45 inch), ZYX channels, a T-pose with the
  legs 20 degrees apart, and the rest pose as frame 0; moving as the bundled walk, so the import
  has a known answer.
* LaFAN1's rest pose with a known answer: `lafan_walk` lays our skeleton's bones along their
  joints' x axes and twists the limbs as the rest pose cannot tell (the legs and feet by half a
  turn, the arms by a quarter), moving as the bundled walk.

`make samples` (tests/samples.py) fetches the two files.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
from samples import BVHTOOLS_DIR, FETCH
from test_bvh import assert_same_poses, body_globals, write_bvh
from test_bvh_real import bone_direction_errors

from orchestrator import clips as motion_cli
from workers.body import rotations as rot
from workers.motion.clip import normalize_quats
from workers.motion.formats import bvh, load_raw
from workers.motion.formats.bvh_names import match_joints
from workers.motion.formats.bvh_retarget import GROUND_PERCENTILE, lowest_points, rest_corrections, swing

# file -> (frames, rate (Hz), unit, the source joints of some of our bodies)
REAL = {
    "test.bvh": (7184, 30.0, "centimetres", {"chest": "Spine2", "left_shoulder": "LeftArm", "left_knee": "LeftLeg"}),
    "test3.bvh": (3089, 24.0, "metres", {"root": "pelvis", "chest": "spine.001", "left_knee": "shin.L"}),
}


def driven(character) -> set[str]:
    """Our bodies that a joint drives (the wrists are welded to the forearms)."""
    return {character.body_names[int(b)] for b in character.body_of_joint} | {"root"}


def joint_angles(character, qpos: np.ndarray, joint: str) -> np.ndarray:
    return qpos[:, character.joint_qpos[character.joint_names.index(joint)].start]


@pytest.fixture(scope="module", params=sorted(REAL))
def real(request, character):
    path = BVHTOOLS_DIR / request.param
    if not path.is_file():
        pytest.fail(f"{path.name} of bvhtools missing: run {FETCH}")
    return path, bvh.load(character, path)


def test_real_file_every_joint_matched_in_its_unit(character, real):
    path, raw = real
    frames, rate, unit, expected = REAL[path.name]
    joints = bvh.parse(path)[0]
    src = match_joints(path, joints, character.body_names)
    matched = {body: joints[j].name for body, j in src.items()}
    assert {k: matched[k] for k in expected} == expected
    assert driven(character) <= set(matched)  # no body of ours left at the identity
    # LaFAN1's legs: 43.50 + 42.37 cm; Rigify's 0.33 + 0.32 m (a small character).
    assert bvh.guess_scale(path, bvh.leg_length(bvh.rest_positions(joints), src)) == bvh.UNITS[unit]
    assert len(raw.qpos) == frames and raw.times[1] == pytest.approx(1.0 / rate, rel=1e-4)
    assert 0.5 < np.median(raw.qpos[:, 2]) < 1.0  # a person's hips, on the ground


def test_real_file_on_the_ground_and_accepted_by_the_checker(character, real):
    path, raw = real
    low = lowest_points(character, raw.qpos)
    assert abs(np.percentile(low, GROUND_PERCENTILE)) < 1e-6 and low.min() > -0.06
    report = motion_cli.check(str(path))  # the plausibility limits a run applies, over the whole clip
    frames, rate, _, _ = REAL[path.name]
    assert report["frames"] == frames and report["rate_hz"] == pytest.approx(rate, rel=1e-3)
    # Measured: LaFAN1 lowest -1.9 cm, median +1.0 cm; Rigify -1.2 cm, +1.6 cm.
    assert -0.03 < report["lowest_foot_m"] < 0.0 < report["median_foot_m"] < 0.03


def test_real_file_limbs_follow_the_source(character, real):
    path, raw = real
    errors = bone_direction_errors(character, path, raw, limbs=("shoulder", "hip", "knee"))  # L then R
    # Medians over the frames. LaFAN1: under 0.1 degree, knees 1.7 and 2.7. Rigify: 0 but the
    # knees, 6.9 and 1.5: they bend 7 degrees (median) and as much sideways as back (the plane
    # keeps 0.7 of its length, under MIN_STEADY), which our hinge knee cannot follow.
    knees = np.array([False, False, True] * 2)
    assert errors[~knees].max() < np.deg2rad(1.0)
    assert errors[knees].max() < np.deg2rad(5.0 if path.name == "test.bvh" else 8.0)
    if path.name == "test.bvh":  # our elbow is one hinge: 7.6 degrees, as far as LaFAN1's forearm leaves a plane
        assert bone_direction_errors(character, path, raw, limbs=("elbow",)).max() < np.deg2rad(10.0)


def test_lafan1_knees_bend_back_and_feet_stand_sole_down(character, real):
    """LaFAN1's legs lie along the spine at rest: a half turn whose axis the rest pose leaves open.
    Read from the rest pose, the knees bent forward (median +0.54 rad, ours bend to negative
    angles) and the feet stood on their tops; the limb planes of the motion settle both."""
    path, raw = real
    knees = [joint_angles(character, raw.qpos, f"{side}_knee") for side in ("left", "right")]
    elbows = [joint_angles(character, raw.qpos, f"{side}_elbow") for side in ("left", "right")]
    if path.name == "test.bvh":
        assert all(np.median(k) < -0.3 and np.percentile(k, 95) < 0.0 for k in knees)  # -0.54, -0.62
        assert all(np.median(e) > 0.5 for e in elbows)  # elbows bend forward (positive): 1.2, 1.8
    else:  # Rigify: legs nearly straight (a median bend of 7 degrees) and upright at rest, as ours
        assert all(abs(np.median(k)) < 0.2 for k in knees)
    data, up = mujoco.MjData(character.model), []
    feet = [character.body_names.index(f"{side}_ankle") + 1 for side in ("left", "right")]
    for q in raw.qpos[:: max(1, len(raw.qpos) // 400)]:
        data.qpos[:] = q
        mujoco.mj_kinematics(character.model, data)
        up.append(data.xmat[feet].reshape(-1, 3, 3)[:, 2, 2])  # the feet's z axis, vertical part
    assert np.median(up) > 0.8  # soles down (upside down: about -1)


# ----------------------------------------------------------------------------
# CMU (the cgspeed conversion's convention), moving as the bundled walk
# ----------------------------------------------------------------------------
CMU_UNITS_PER_METRE = 0.45 / 0.0254
SPREAD = np.deg2rad(20.0)  # CMU's rest pose has the legs 20 degrees apart


def cmu_walk(character, walk):
    """(skeleton for write_bvh, global rotations [T + 1, J, 4], root positions [T + 1, 3]).

    Each matched joint turns as its body of ours in the walk times the rest correction: the
    T-pose arms a quarter turn about x, the spread legs 20 degrees. Frame 0 is the rest pose.
    """
    w = body_globals(character, normalize_quats(character, walk.qpos))
    b = {name: w[:, i] for i, name in enumerate(character.body_names)}
    ch = "Zrotation Yrotation Xrotation".split()
    toe = np.array([0.1335, 0.0, -0.05])  # our foot's End Site: a toe along it keeps the foot's rest
    rows = [
        ("Hips", None, (0, 0, 0), None, b["root"]),
        ("LowerBack", "Hips", (0, 0, 0), None, b["root"]),
        ("Spine", "LowerBack", (0, 0, 0.12), None, rot.slerp(b["root"], b["chest"], 0.5)),
        ("Spine1", "Spine", (0, 0, 0.12), None, b["chest"]),
        ("Neck", "Spine1", (0, 0, 0), None, b["neck"]),  # zero-length, on Spine1
        ("Neck1", "Neck", (0, 0, 0.09), None, b["neck"]),
        ("Head", "Neck1", (0, 0, 0.09), (0, 0, 0.16), b["neck"]),
    ]
    for s, sign in (("Left", 1), ("Right", -1)):
        quarter = rot.from_expmap(np.array([sign * np.pi / 2, 0.0, 0.0]))  # down -> sideways
        spread = rot.from_expmap(np.array([sign * SPREAD, 0.0, 0.0]))
        lateral, leg_dir = np.array([0.0, sign, 0.0]), rot.rotate(spread, np.array([0.0, 0.0, -1.0]))
        arm = {k: rot.mul(b[f"{s.lower()}_{k}"], rot.conj(quarter)) for k in ("shoulder", "elbow", "wrist")}
        leg = {k: rot.mul(b[f"{s.lower()}_{k}"], rot.conj(spread)) for k in ("hip", "knee")}
        rows += [
            (f"{s}Shoulder", "Spine1", (0, 0, 0), None, b["chest"]),
            (f"{s}Arm", f"{s}Shoulder", 0.17 * lateral + [0, 0, 0.06], None, arm["shoulder"]),
            (f"{s}ForeArm", f"{s}Arm", 0.28 * lateral, None, arm["elbow"]),
            (f"{s}Hand", f"{s}ForeArm", 0.24 * lateral, None, arm["wrist"]),
            (f"{s}FingerBase", f"{s}Hand", 0.05 * lateral, (0.04 * lateral), arm["wrist"]),
            (f"{s[0]}Thumb", f"{s}Hand", 0.03 * lateral + [0.02, 0, 0], (0.03, 0, 0), arm["wrist"]),
            (f"{s[0]}HipJoint", "Hips", (0, 0, 0), None, b["root"]),
            (f"{s}UpLeg", f"{s[0]}HipJoint", (0.0, sign * 0.09, -0.07), None, leg["hip"]),
            (f"{s}Leg", f"{s}UpLeg", 0.43 * leg_dir, None, leg["knee"]),
            (f"{s}Foot", f"{s}Leg", 0.41 * leg_dir, None, b[f"{s.lower()}_ankle"]),
            (f"{s}ToeBase", f"{s}Foot", 0.9 * toe, (0.05, 0, 0), b[f"{s.lower()}_ankle"]),
        ]
    names = [r[0] for r in rows]
    at = ["Xposition", "Yposition", "Zposition"]
    skel = [
        [n, names.index(p) if p else -1, np.asarray(o, float), (at if p is None else []) + ch, e]
        for n, p, o, e, _ in rows
    ]
    glob, root = np.stack([r[4] for r in rows], axis=1), walk.qpos[:, :3]  # the import grounds it
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (1, len(rows), 1))  # frame 0: the rest pose, all channels zero
    return skel, np.concatenate((identity, glob)), np.concatenate((root[:1], root))


@pytest.fixture(scope="module")
def cmu_file(character, tmp_path_factory):
    walk = load_raw(character, "humanoid3d_walk")
    skel, glob, root = cmu_walk(character, walk)
    path = tmp_path_factory.mktemp("cmu") / "cmu_walk.bvh"
    write_bvh(path, skel, glob, root, walk.times[1], scale=CMU_UNITS_PER_METRE)
    return path, walk


def test_cmu_file_imports_as_the_walk_on_the_ground(character, cmu_file, caplog):
    path, walk = cmu_file
    joints = bvh.parse(path)[0]
    src = {b: joints[j].name for b, j in match_joints(path, joints, character.body_names).items()}
    assert src["chest"] == "Spine1" and src["neck"] == "Neck" and src["left_shoulder"] == "LeftArm"
    assert src["left_hip"] == "LeftUpLeg" and src["right_ankle"] == "RightFoot" and driven(character) <= set(src)
    with caplog.at_level("INFO"):
        raw = bvh.load(character, path)
    assert "read in CMU units" in caplog.text and "frame 0 is a pose put before the motion" in caplog.text
    lift = -np.percentile(lowest_points(character, normalize_quats(character, walk.qpos)), GROUND_PERCENTILE)
    expected = walk.qpos.copy()
    expected[:, 2] += lift
    assert_same_poses(character, expected, raw.qpos, rot_tol=1e-6, pos_tol=1e-6)
    report = motion_cli.check(str(path))
    assert report["frames"] == len(walk.qpos) and -0.01 < report["lowest_foot_m"] < 0.01


def test_file_unit_is_read_from_the_legs_not_the_height(character, cmu_file, tmp_path):
    """The CMU file with its rest pose laid along x (as LaFAN1's): the same legs, the same unit."""
    path, _ = cmu_file
    joints = bvh.parse(path)[0]
    src = match_joints(path, joints, character.body_names)
    leg = bvh.leg_length(bvh.rest_positions(joints), src)
    assert leg == pytest.approx((0.43 + 0.41) * CMU_UNITS_PER_METRE, rel=1e-9)
    flat = [bvh.Joint(j.name, j.parent, np.array([np.linalg.norm(j.offset), 0.0, 0.0])) for j in joints]
    assert bvh.leg_length(bvh.rest_positions(flat), src) == pytest.approx(leg, rel=1e-9)
    assert np.ptp(bvh.rest_positions(flat)[:, 1]) == 0.0  # no height at all
    assert bvh.guess_scale(Path(path), leg) == bvh.UNITS["CMU units"]


def test_legs_human_in_no_unit_are_one_line_naming_the_file(character, tmp_path, capsys):
    """The CMU walk at 3.5 units a metre: legs of 2.9 units, 2.9 m in metres, 7.5 cm in inches,
    17 cm in CMU units. The checker says so in one line, nothing is imported."""
    walk = load_raw(character, "humanoid3d_walk")
    skel, glob, root = cmu_walk(character, walk)
    path = tmp_path / "tiny_units.bvh"
    write_bvh(path, skel, glob, root, walk.times[1], scale=3.5)
    assert motion_cli.main(["check", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert "tiny_units.bvh" in err and "cannot tell the file's unit" in err and "\n" not in err
    raw = bvh.load(character, path, scale=1.0 / 3.5)  # an explicit scale still imports it
    assert 0.5 < np.median(raw.qpos[:, 2]) < 1.0


# ----------------------------------------------------------------------------
# LaFAN1's rest pose with a known answer: every bone along x, limbs twisted as the rest cannot tell
# ----------------------------------------------------------------------------
LAFAN_NAMES = {
    "root": "Hips", "chest": "Spine2", "neck": "Neck", "left_shoulder": "LeftArm", "left_elbow": "LeftForeArm",
    "left_wrist": "LeftHand", "right_shoulder": "RightArm", "right_elbow": "RightForeArm",
    "right_wrist": "RightHand", "left_hip": "LeftUpLeg", "left_knee": "LeftLeg", "left_ankle": "LeftFoot",
    "right_hip": "RightUpLeg", "right_knee": "RightLeg", "right_ankle": "RightFoot",
}  # fmt: skip
# The limbs' turn about their bones beyond what the rest pose suggests: half a turn for the
# legs and feet (LaFAN1's: the knees bend the other way, the feet lie sole up), a quarter for the arms.
TWIST = {"hip": np.pi, "knee": np.pi, "ankle": np.pi, "shoulder": np.pi / 2, "elbow": np.pi / 2}


def lafan_walk(character, walk):
    """(skeleton for write_bvh, global rotations [T, J, 4], the rest pose's guess, the true corrections).

    Our skeleton, LaFAN1's names, each body's frame turned by C_b so that its bone lies along
    its x axis (the hips: spine along x, left along -y as LaFAN1's file has it); the source's
    joints turn as G_ours C_b^-1.
    """
    names, parent = character.body_names, character.model.body_parentid[1:] - 1
    kids = {b: [c for c in range(1, len(names)) if parent[c] == b] for b in range(len(names))}
    x = np.array([1.0, 0.0, 0.0])
    frame = {0: rot.from_matrix(np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]]))}
    for b in range(1, len(names)):
        bone = character.model.body_pos[kids[b][0] + 1] if kids[b] else np.asarray(bvh.END_SITES[names[b]])
        frame[b] = swing(bone, x)
    skel = []
    for b, body in enumerate(names):
        offset = np.zeros(3) if b == 0 else rot.rotate(frame[parent[b]], character.model.body_pos[b + 1])
        end = rot.rotate(frame[b], np.asarray(bvh.END_SITES[body])) if not kids[b] else None
        channels = ("Xposition Yposition Zposition " if b == 0 else "") + "Zrotation Yrotation Xrotation"
        skel.append([LAFAN_NAMES[body], int(parent[b]) if b else -1, offset, channels.split(), end])
    joints = [bvh.Joint(n, p, o) for n, p, o, *_ in skel]
    joints += [
        bvh.Joint(f"{n}/End Site", j, e, end_site=True) for j, (n, _, _, _, e) in enumerate(skel) if e is not None
    ]
    guess = rest_corrections(character, joints, bvh.rest_positions(joints), {n: i for i, n in enumerate(names)})
    truth = {}
    for b, body in enumerate(names):
        kind = body.split("_", 1)[-1]
        truth[b] = rot.mul(rot.from_expmap(TWIST.get(kind, 0.0) * x), guess[b]) if kind in TWIST else guess[b]
    w = body_globals(character, normalize_quats(character, walk.qpos))
    glob = np.stack([rot.mul(w[:, b], rot.conj(truth[b])) for b in range(len(names))], axis=1)
    return skel, glob, guess, truth


def test_lafan1_rest_pose_imports_as_the_walk(character, tmp_path):
    walk = load_raw(character, "humanoid3d_walk")
    skel, glob, guess, truth = lafan_walk(character, walk)
    parent = [row[1] for row in skel]
    first = [b for b in range(1, len(skel)) if b == parent.index(parent[b])]  # first children: the bones
    bones = [skel[b][2] for b in first] + [row[4] for row in skel if row[4] is not None]
    assert all(v[0] > 0.0 and np.abs(v[1:]).max() < 1e-12 for v in bones)  # every bone along its joint's x
    path = tmp_path / "lafan_walk.bvh"
    write_bvh(path, skel, glob, walk.qpos[:, :3], walk.times[1], scale=100.0)
    # What the rest pose alone guesses is off by the twists (a half turn for the legs).
    legs = [b for b, name in enumerate(character.body_names) if name.endswith(("hip", "knee", "ankle"))]
    assert all(rot.angle(rot.mul(guess[b], rot.conj(truth[b]))) > 3.0 for b in legs)
    raw = bvh.load(character, path)
    lift = -np.percentile(lowest_points(character, normalize_quats(character, walk.qpos)), GROUND_PERCENTILE)
    expected = walk.qpos.copy()
    expected[:, 2] += lift
    assert_same_poses(character, expected, raw.qpos, rot_tol=1e-6, pos_tol=1e-6)
