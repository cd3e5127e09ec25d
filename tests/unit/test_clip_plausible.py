"""Clips whose values are finite but absurd are refused with the frame named; no bundled clip is."""

from __future__ import annotations

import numpy as np
import pytest

from workers.motion import clip as clip_mod
from workers.motion.clip import RawClip, check_plausible, validate_raw
from workers.motion.errors import ClipError
from workers.motion.formats import bundled_clip_names, load_raw

FPS = 30.0


def standing(character, frames: int) -> RawClip:
    """The model's default pose held for `frames` frames at 30 Hz (root at qpos0)."""
    qpos = np.tile(character.model.qpos0, (frames, 1))
    return RawClip("synthetic", qpos, np.arange(frames) / FPS, loop=False, source="synthetic.npz")


def test_no_bundled_clip_is_refused(character):
    names = bundled_clip_names()
    assert len(names) == 20 and "walker/turn_left0" in names and "humanoid3d_backflip" in names
    for name in names:
        raw = load_raw(character, name)
        validate_raw(character, raw)  # raises ClipError on an implausible clip
        mirrored = clip_mod.mirror_raw(character, raw)
        check_plausible(character, mirrored)


def test_the_fastest_bundled_joint_is_well_below_the_limit(character):
    # The limit's comment quotes 30.5 rad/s (left shoulder, humanoid3d_backflip, 16 Hz): measured here.
    raw = load_raw(character, "humanoid3d_backflip")
    qpos = clip_mod.normalize_quats(character, raw.qpos)
    qvel = np.zeros((len(qpos) - 1, character.model.nv))
    for t, dt in enumerate(np.diff(raw.times)):
        clip_mod.mujoco.mj_differentiatePos(character.model, qvel[t], dt, qpos[t], qpos[t + 1])
    speeds = [np.linalg.norm(qvel[:, dofs], axis=1).max() for dofs in character.joint_dof]
    assert max(speeds) == pytest.approx(30.5, abs=0.1)
    assert character.joint_names[int(np.argmax(speeds))] == "left_shoulder"
    assert max(speeds) < clip_mod.MAX_JOINT_SPEED_RAD_S / 1.5


@pytest.mark.parametrize("speed,refused", [(29.0, False), (31.0, True)])
def test_root_speed_limit(character, speed, refused):
    raw = standing(character, 10)
    raw.qpos[5:, 0] += speed / FPS  # one jump of `speed` m/s from frame 4 to frame 5
    if not refused:
        check_plausible(character, raw)
        return
    with pytest.raises(ClipError, match=r"frame 5: root moves at 31 m/s from frame 4 \(more than 30 m/s\)"):
        check_plausible(character, raw)


@pytest.mark.parametrize("joint", ["right_knee", "left_shoulder"])
@pytest.mark.parametrize("speed,refused", [(49.0, False), (51.0, True)])
def test_joint_speed_limit(character, joint, speed, refused):
    raw = standing(character, 6)
    j = character.joint_names.index(joint)
    sl = character.joint_qpos[j]
    angle = speed / FPS * np.arange(6)  # turning at `speed` rad/s throughout
    if character.joint_types[j] == "hinge":
        raw.qpos[:, sl] = angle[:, None]
    else:  # about x: (cos θ/2, sin θ/2, 0, 0)
        raw.qpos[:, sl] = np.stack([np.cos(angle / 2), np.sin(angle / 2), 0 * angle, 0 * angle], axis=1)
    if not refused:
        check_plausible(character, raw)
        return
    with pytest.raises(ClipError, match=rf"frame 1: {joint} turns at 51 rad/s from frame 0 \(more than 50 rad/s\)"):
        check_plausible(character, raw)


def test_root_far_from_the_origin_or_from_its_start(character):
    raw = standing(character, 4)
    raw.qpos[:, 0] = 999.0
    check_plausible(character, raw)
    raw.qpos[2:, 0] = 1001.0  # and a jump of 60 m/s: the distance is found first
    with pytest.raises(ClipError, match=r"synthetic.npz: frame 2: root is 1e\+03 m from the origin"):
        check_plausible(character, raw)

    raw = standing(character, int(4.2 * FPS))
    raw.qpos[:, 0] = 25.0 * raw.times  # 25 m/s: below the speed limit, past 100 m after 4 s
    # Frame 121 is the first beyond 100 m from frame 0 (25 m/s * 121 / 30 Hz = 100.8 m).
    with pytest.raises(ClipError, match=r"frame 121: root is 101 m from its position in frame 0"):
        check_plausible(character, raw)


def test_the_run_and_the_checker_refuse_alike(character, tmp_path):
    """Both go through clip.process (the library's load and `orchestrator.clips check`)."""
    from workers.motion.formats import npz
    from workers.motion.library import MotionLibrary

    raw = standing(character, 10)
    raw.qpos[7:, 1] += 3.0  # 3 m sideways in 1/30 s
    path = tmp_path / "jump.npz"
    npz.save(character, raw, path, fps=FPS)
    with pytest.raises(ClipError, match=r"jump.npz: frame 7: root moves at 90 m/s from frame 6"):
        MotionLibrary.load(character, [str(path)], fps=FPS, cache_dir=tmp_path / "cache")
    assert not (tmp_path / "cache").exists()  # nothing cached: the next run checks it again
    from orchestrator.clips import check

    with pytest.raises(ClipError, match=r"jump.npz: frame 7: root moves at 90 m/s from frame 6"):
        check(str(path))
