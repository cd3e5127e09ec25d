"""BVH import of skeletons from other tools: naming conventions, grounding, the joint map's wiring.

* Two third-party files, written by nobody here: the Mixamo export and the mocap-bank clip
  (Collar/Shoulder/Elbow/Wrist, Hip/Knee/Ankle) that `bvhtoolbox`'s source distribution on
  PyPI ships as test data (`make samples`, part of `make setup`, fetches them; tests/samples.py).
  No package on PyPI ships BVH clips in its installed files (searched: bvh, bvhio, pybvh,
  pybvh-ml, bvhtoolbox's wheel, bvhsdk, bvhtools, bvh-converter, fairmotion, mcp-persor, ...).
* The naming conventions are checked on the hierarchies of real exports (test_bvh_names.py).
* Whole clips are written here in the Mixamo and mocap-bank styles (their names, nesting,
  T-pose or arms-down rest poses, clavicles, extra spine and toe joints, centimetres, legs
  longer than ours) moving as the bundled walk, so the import has a known answer.
* Files of your own run through the same checks with MOCAP_BVH_DIR=/a/folder/of/bvh
  (skipped without it).
"""

from __future__ import annotations

import json
import os
import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest
from samples import BVH_DIR, FETCH
from test_bvh import assert_same_poses, body_globals, write_bvh

from orchestrator import clips as motion_cli
from orchestrator.world import load_character_and_library
from workers.body import rotations as rot
from workers.motion.clip import normalize_quats, process
from workers.motion.errors import ClipError
from workers.motion.formats import bvh, load_raw
from workers.motion.formats.bvh_names import match_joints
from workers.motion.formats.bvh_retarget import GROUND_PERCENTILE, lowest_points
from workers.motion.formats.deepmimic import Y_TO_Z
from workers.motion.library import MotionLibrary


# ----------------------------------------------------------------------------
# Whole clips in the Mixamo and mocap-bank styles, moving as the bundled walk
# ----------------------------------------------------------------------------
def styled_clip(character, walk, style: str):
    """(skeleton for write_bvh, global rotations [T, J, 4], root positions [T, 3]) of the walk.

    Every joint matched to a body of ours turns as that body does in the walk (times the rest
    correction where the rest pose differs: the T-pose arms), so the import's answer is the walk.
    The source's legs are longer than ours and its feet stand on the ground, as in a capture.
    """
    w = body_globals(character, normalize_quats(character, walk.qpos))
    b = {name: w[:, i] for i, name in enumerate(character.body_names)}
    t = np.arange(len(walk.qpos))[:, None]
    wobble = rot.from_expmap(0.15 * np.sin(0.4 * t) * np.array([1.0, 0.5, 0.0]))  # clavicles, toes, head
    down = np.array([0.1335, 0.0, -0.05])  # our foot's End Site: a toe joint along it keeps the foot's rest
    ch = "Zrotation Xrotation Yrotation".split()
    rows = []  # name, parent name, offset (z-up, m), End Site or None, global rotation [T, 4]
    if style == "mixamo":
        # T-pose arms: our rest arm (down) turns onto theirs (sideways) by a quarter turn about x.
        quarter = {
            s: rot.from_expmap(np.array([sign * np.pi / 2, 0.0, 0.0])) for s, sign in (("Left", 1), ("Right", -1))
        }
        rows += [
            ("Hips", None, (0, 0, 0), None, b["root"]),
            ("Spine", "Hips", (0, 0, 0.10), None, rot.slerp(b["root"], b["chest"], 1 / 3)),
            ("Spine1", "Spine", (0, 0, 0.12), None, rot.slerp(b["root"], b["chest"], 2 / 3)),
            ("Spine2", "Spine1", (0, 0, 0.12), None, b["chest"]),
            ("Neck", "Spine2", (0, 0, 0.15), None, b["neck"]),
            ("Head", "Neck", (0, 0, 0.10), (0, 0, 0.18), rot.mul(b["neck"], wobble)),
        ]
        for s, sign in (("Left", 1), ("Right", -1)):
            arm = {k: rot.mul(b[f"{s.lower()}_{k}"], rot.conj(quarter[s])) for k in ("shoulder", "elbow", "wrist")}
            rows += [
                (f"{s}Shoulder", "Spine2", (0, sign * 0.03, 0.10), None, rot.mul(b["chest"], wobble)),
                (f"{s}Arm", f"{s}Shoulder", (0, sign * 0.13, 0), None, arm["shoulder"]),
                (f"{s}ForeArm", f"{s}Arm", (0, sign * 0.27, 0), None, arm["elbow"]),
                (f"{s}Hand", f"{s}ForeArm", (0, sign * 0.25, 0), None, arm["wrist"]),
                (f"{s}HandIndex1", f"{s}Hand", (0, sign * 0.09, 0), (0, sign * 0.03, 0), arm["wrist"]),
            ]
        for s, sign in (("Right", -1), ("Left", 1)):  # Mixamo lists the right leg first
            leg = {k: b[f"{s.lower()}_{k}"] for k in ("hip", "knee", "ankle")}
            rows += [
                (f"{s}UpLeg", "Hips", (0, sign * 0.09, -0.05), None, leg["hip"]),
                (f"{s}Leg", f"{s}UpLeg", (0, 0, -0.44), None, leg["knee"]),
                (f"{s}Foot", f"{s}Leg", (0, 0, -0.42), None, leg["ankle"]),
                (f"{s}ToeBase", f"{s}Foot", 0.9 * down, (0.05, 0, 0), rot.mul(leg["ankle"], wobble)),
            ]
        rows = [(f"mixamorig:{n}", p and f"mixamorig:{p}", *rest) for n, p, *rest in rows]
        legs, sole = 0.05 + 0.44 + 0.42, 0.9 * 0.05
    else:  # mocap-bank: Collar/Shoulder/Elbow/Wrist, Hip/Knee/Ankle, arms down at rest
        rows += [
            ("Hips", None, (0, 0, 0), None, b["root"]),
            ("Chest", "Hips", (0, 0, 0.10), None, rot.slerp(b["root"], b["chest"], 0.5)),
            ("Chest2", "Chest", (0, 0, 0.16), None, b["chest"]),
        ]
        for s, sign in (("Left", 1), ("Right", -1)):
            rows += [
                (f"{s}Collar", "Chest2", (0, 0, 0.17), None, rot.mul(b["chest"], wobble)),
                (f"{s}Shoulder", f"{s}Collar", (0, sign * 0.16, -0.03), None, b[f"{s.lower()}_shoulder"]),
                (f"{s}Elbow", f"{s}Shoulder", (0, 0, -0.255), None, b[f"{s.lower()}_elbow"]),
                (f"{s}Wrist", f"{s}Elbow", (0, 0, -0.225), (0, 0, -0.14), b[f"{s.lower()}_wrist"]),
            ]
        rows += [
            ("Neck", "Chest2", (0, 0, 0.17), None, b["neck"]),
            ("Head", "Neck", (0, 0, 0.11), (0, 0, 0.18), b["neck"]),
        ]
        for s, sign in (("Left", 1), ("Right", -1)):
            rows += [
                (f"{s}Hip", "Hips", (0, sign * 0.09, 0), None, b[f"{s.lower()}_hip"]),
                (f"{s}Knee", f"{s}Hip", (0, 0, -0.47), None, b[f"{s.lower()}_knee"]),
                (f"{s}Ankle", f"{s}Knee", (0, 0, -0.41), tuple(1.2 * down), b[f"{s.lower()}_ankle"]),
            ]
        legs, sole = 0.47 + 0.41, 1.2 * 0.05
    names = [r[0] for r in rows]
    at = ["Xposition", "Yposition", "Zposition"]
    skel = [
        [n, names.index(p) if p else -1, np.asarray(o, float), (at if p is None else []) + ch, e]
        for n, p, o, e, _ in rows
    ]
    ours = 0.421546 + 0.40987 + 0.05  # hip to knee to ankle to sole
    root = walk.qpos[:, :3] + [0.0, 0.0, legs + sole - ours]  # the source's feet where ours are
    return skel, np.stack([r[4] for r in rows], axis=1), root


@pytest.fixture(scope="module")
def walk(character):
    return load_raw(character, "humanoid3d_walk")


@pytest.fixture(scope="module")
def bundled_walk_report():
    return motion_cli.check("humanoid3d_walk")


@pytest.fixture(scope="module", params=["mixamo", "mocap_bank"])
def styled(request, character, walk, tmp_path_factory):
    skel, glob, root = styled_clip(character, walk, request.param)
    path = tmp_path_factory.mktemp(request.param) / f"{request.param}_walk.bvh"
    write_bvh(path, skel, glob, root, walk.times[1], scale=100.0)  # centimetres, y-up
    return request.param, path


def test_styled_clip_imports_as_the_walk_on_the_ground(character, walk, styled):
    style, path = styled
    joints = bvh.parse(path)[0]
    src = {b: joints[j].name for b, j in match_joints(path, joints, character.body_names).items()}
    chest, arm = ("mixamorig:Spine2", "mixamorig:LeftArm") if style == "mixamo" else ("Chest2", "LeftShoulder")
    assert src["chest"] == chest and src["left_shoulder"] == arm and len(src) == character.num_bodies
    back = bvh.load(character, path)
    # The walk's poses exactly (no shoulder left at the identity), lifted as the walk itself is grounded.
    lift = -np.percentile(lowest_points(character, normalize_quats(character, walk.qpos)), GROUND_PERCENTILE)
    expected = walk.qpos.copy()
    expected[:, 2] += lift
    assert_same_poses(character, expected, back.qpos, rot_tol=1e-6, pos_tol=1e-6)
    # Without grounding the feet float by the leg-length difference (Mixamo 7.5 cm, mocap-bank 5.8 cm).
    floating = process(character, bvh.load(character, path, ground=None), 30).foot_min_z.min()
    assert floating > 0.04


def test_styled_clip_passes_the_checker_at_the_bundled_level(styled, bundled_walk_report):
    _, path = styled
    report = motion_cli.check(str(path))
    assert report["frames"] == 39 and report["rate_hz"] == pytest.approx(30.0, rel=1e-3)
    # humanoid3d_walk: lowest -0.53 cm, median +0.71 cm; its import is lifted by 0.40 cm.
    assert abs(report["lowest_foot_m"] - bundled_walk_report["lowest_foot_m"]) < 0.01
    assert abs(report["median_foot_m"] - bundled_walk_report["median_foot_m"]) < 0.01
    assert -0.01 < report["lowest_foot_m"] < 0.01


def test_styled_clip_is_a_walk(character, styled):
    _, path = styled
    raw = bvh.load(character, path)
    assert np.linalg.norm(raw.qpos[-1, :2] - raw.qpos[0, :2]) > 1.0  # walks over a metre in 1.3 s
    for side in ("left", "right"):
        knee = raw.qpos[:, character.joint_qpos[character.joint_names.index(f"{side}_knee")].start]
        assert np.ptp(knee) > 0.8 and knee.max() < 0.3  # bends (our knees flex to negative angles)
    assert bone_direction_errors(character, path, raw).max() < 1e-4


# ----------------------------------------------------------------------------
# The joint map through the command line, the library (and its cache) and load_world
# ----------------------------------------------------------------------------
@pytest.fixture
def renamed(styled, tmp_path):
    """The styled clip with its knees renamed to something no convention knows."""
    style, path = styled
    text = path.read_text()
    for side in ("Left", "Right"):
        knee = f"mixamorig:{side}Leg" if style == "mixamo" else f"{side}Knee"
        text, n = re.subn(rf"JOINT\s+{knee}\b", f"JOINT {side[0]}Segment4", text)
        assert n == 1
    out = tmp_path / "renamed.bvh"
    out.write_text(text)
    return out


def test_cli_joint_map(renamed, capsys):
    assert motion_cli.main(["check", str(renamed)]) == 1
    err = capsys.readouterr().err
    assert "renamed.bvh" in err and "for right_knee, left_knee," in err and "joint_map" in err
    mapping = json.dumps({"LSegment4": "left_knee", "RSegment4": "right_knee"})
    assert motion_cli.main(["check", str(renamed), "--joint-map", mapping]) == 0
    assert "feet      lowest" in capsys.readouterr().out
    as_file = renamed.with_suffix(".json")
    as_file.write_text(mapping)
    assert motion_cli.main(["check", str(renamed), "--joint-map", str(as_file), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 39


def test_library_and_load_world_pass_the_joint_map_and_key_the_cache_on_it(character, renamed, tmp_path):
    cache = tmp_path / "cache"
    with pytest.raises(ClipError, match="left_knee"):
        MotionLibrary.load(character, [str(renamed)], fps=30, cache_dir=cache)
    knees = {"LSegment4": "left_knee", "RSegment4": "right_knee"}
    lib = MotionLibrary.load(character, [str(renamed)], fps=30, cache_dir=cache, joint_map=knees)
    assert len(list(cache.glob("*.npz"))) == 1
    # Another map makes another cache entry, not the stale one: knees crossed over.
    crossed = {"LSegment4": "right_knee", "RSegment4": "left_knee"}
    other = MotionLibrary.load(character, [str(renamed)], fps=30, cache_dir=cache, joint_map=crossed)
    assert len(list(cache.glob("*.npz"))) == 2
    k = character.joint_qpos[character.joint_names.index("left_knee")].start
    assert np.abs(lib.clips[0].qpos[:, k] - other.clips[0].qpos[:, k]).max() > 0.1
    again = MotionLibrary.load(character, [str(renamed)], fps=30, cache_dir=cache, joint_map=knees)
    np.testing.assert_array_equal(again.clips[0].qpos, lib.clips[0].qpos)

    cfg = SimpleNamespace(
        character=SimpleNamespace(self_collision=False, xml=None, control_hz=30),
        motion=SimpleNamespace(clips=[str(renamed)], mirror=False, cache_dir=str(cache), joint_map=knees),
    )
    _, world = load_character_and_library(cfg)
    np.testing.assert_array_equal(world.clips[0].qpos, lib.clips[0].qpos)
    cfg.motion.joint_map = {}
    with pytest.raises(ClipError, match="right_knee"):
        load_character_and_library(cfg)


# ----------------------------------------------------------------------------
# Third-party files: bvhtoolbox's test data (make samples)
# ----------------------------------------------------------------------------
# file -> (frames, the source joints our chest and shoulders take: the mocap-bank file's
# Shoulder is the upper arm, its Collar the clavicle; Mixamo's upper arm is Arm)
THIRD_PARTY = {
    "test_freebvh.bvh": (69, {"chest": "mixamorig:Spine2", "left_shoulder": "mixamorig:LeftArm"}),
    "test_mocapbank.bvh": (455, {"chest": "Chest2", "left_shoulder": "LeftShoulder", "right_hip": "RightHip"}),
}


def sample(name: str) -> Path:
    path = BVH_DIR / name
    if not path.is_file():
        pytest.fail(f"{path.relative_to(BVH_DIR.parents[2])} missing: run {FETCH}")
    return path


@pytest.mark.parametrize("name", sorted(THIRD_PARTY))
def test_third_party_file(character, name, tmp_path):
    path, (frames, expected) = sample(name), THIRD_PARTY[name]
    joints, _, _ = bvh.parse(path)
    matched = {ours: joints[i].name for ours, i in match_joints(path, joints, character.body_names).items()}
    assert {k: matched[k] for k in expected} == expected
    assert {b for b in character.body_names} <= set(matched) | {"root"}  # every body of ours has a source
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no body left at identity "with only a warning"
        raw = bvh.load(character, path)
    assert len(raw.qpos) == frames
    # Both shoulders move (the mocap-bank file's were lost to the identity rotation before).
    for side in ("left", "right"):
        q = raw.qpos[:, character.joint_qpos[character.joint_names.index(f"{side}_shoulder")]]
        assert np.abs(q - [1.0, 0.0, 0.0, 0.0]).max() > 0.05
    # On the ground (they floated 4-8 cm), in metres (the files are in centimetres), limbs aligned.
    low = lowest_points(character, raw.qpos)
    assert abs(np.percentile(low, GROUND_PERCENTILE)) < 1e-6 and low.min() > -0.01
    assert 0.4 < raw.qpos[:, 2].min() and raw.qpos[:, 2].max() < 1.0
    assert bone_direction_errors(character, path, raw).max() < np.deg2rad(5.0)
    # Our elbow is one hinge; a forearm that the source turns out of its plane is followed within 10 degrees.
    assert bone_direction_errors(character, path, raw, limbs=("elbow",)).max() < np.deg2rad(10.0)
    report = motion_cli.check(str(path))  # the checker's plausibility limits, as a run applies them
    assert report["frames"] == frames and abs(report["rate_hz"] - 30.0) < 1e-3
    lib = MotionLibrary.load(character, [str(path)], fps=30, cache_dir=tmp_path)
    assert lib.clips[0].qpos.shape == raw.qpos.shape


# ----------------------------------------------------------------------------
# Your own files: MOCAP_BVH_DIR=/folder/of/bvh pytest tests/unit/test_bvh_real.py
# ----------------------------------------------------------------------------
def bone_direction_errors(character, path, raw, limbs=("shoulder", "hip", "knee")) -> np.ndarray:
    """Median angle (rad) over the frames between each of our limb bones and the source's, per bone."""
    joints, frames, _ = bvh.parse(path)
    src = match_joints(path, joints, character.body_names)
    pos = bvh.forward_kinematics(joints, frames)[1][len(frames) - len(raw.qpos) :] @ Y_TO_Z.T
    data, xpos = mujoco.MjData(character.model), np.zeros((len(raw.qpos), character.num_bodies, 3))
    for t, q in enumerate(raw.qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(character.model, data)
        xpos[t] = data.xpos[1:]
    child = {"shoulder": "elbow", "elbow": "wrist", "hip": "knee", "knee": "ankle"}
    out = []
    for side in ("left", "right"):
        for kind in limbs:
            a, b = (character.body_names.index(f"{side}_{k}") for k in (kind, child[kind]))
            ours = xpos[:, b] - xpos[:, a]
            theirs = pos[:, src[f"{side}_{child[kind]}"]] - pos[:, src[f"{side}_{kind}"]]
            cos = (ours * theirs).sum(-1) / np.linalg.norm(ours, axis=-1) / np.linalg.norm(theirs, axis=-1)
            out.append(np.median(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.array(out)


_DIR = os.environ.get("MOCAP_BVH_DIR")
OWN_FILES = sorted(Path(_DIR).glob("*.bvh")) if _DIR else []


NO_FILES = [pytest.param(None, marks=pytest.mark.skip(reason="set MOCAP_BVH_DIR to check your own BVH files"))]


@pytest.mark.parametrize("path", OWN_FILES or NO_FILES, ids=str)
def test_own_files(character, path):
    raw = bvh.load(character, path)  # every essential body matched, or a ClipError
    low = lowest_points(character, raw.qpos)
    assert abs(np.percentile(low, GROUND_PERCENTILE)) < 1e-6 and low.min() > -0.1
    assert bone_direction_errors(character, path, raw).max() < np.deg2rad(5.0)
    report = motion_cli.check(str(path))  # the checker's plausibility limits too
    assert report["median_foot_m"] > -0.02
