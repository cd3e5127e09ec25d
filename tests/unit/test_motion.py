"""Motion data: bundled clips, axes and scale, mirroring, velocities, looping, sampling, cache."""

import copy

import mujoco
import numpy as np
import pytest

from workers.motion.clip import mirror_qpos, process
from workers.motion.formats import bundled_clip_names, load_raw
from workers.motion.library import MotionLibrary, balancing_weights, load_clip

BUNDLED = bundled_clip_names()


def test_all_bundled_clips_are_found():
    assert len([n for n in BUNDLED if n.startswith("humanoid3d_")]) == 15
    assert sorted(n for n in BUNDLED if n.startswith("walker/")) == [
        "walker/0walk_forward", "walker/turn_left0", "walker/turn_left1", "walker/turn_right0", "walker/turn_right1",
    ]  # fmt: skip


def test_the_bundled_clips_can_come_from_a_folder_named_in_the_environment(character, tmp_path, monkeypatch):
    """MOCAP_MOTION_DIR: a copy of pybullet_data's clips, for a machine without pybullet (the GPU machine)."""
    import shutil

    from workers.motion.errors import ClipError
    from workers.motion.formats import bundled_motion_dir

    shutil.copy(bundled_motion_dir() / "humanoid3d_walk.txt", tmp_path)
    monkeypatch.setenv("MOCAP_MOTION_DIR", str(tmp_path))
    assert bundled_clip_names() == ["humanoid3d_walk"]
    (tmp_path / "humanoid3d_walk.txt").write_text("not a clip")  # the folder's file is the one read
    with pytest.raises(ClipError, match="humanoid3d_walk"):
        load_raw(character, "humanoid3d_walk")
    monkeypatch.setenv("MOCAP_MOTION_DIR", str(tmp_path / "missing"))
    with pytest.raises(ClipError, match="MOCAP_MOTION_DIR names no folder"):
        bundled_clip_names()


@pytest.mark.parametrize("name", BUNDLED)
def test_every_bundled_clip_loads(character, clip_cache, name):
    clip = load_clip(character, name, fps=30, cache_dir=clip_cache)
    assert clip.num_frames >= 20
    for field in ("qpos", "qvel", "xpos", "xquat", "lin_vel", "ang_vel"):
        assert np.isfinite(getattr(clip, field)).all(), field
    # The root starts above the ground and every clip keeps the feet near it at some point.
    assert clip.qpos[0, 2] > 0.05
    assert clip.foot_min_z.min() < 0.15


@pytest.mark.parametrize("name", ["humanoid3d_walk", "humanoid3d_run"])
def test_feet_touch_the_ground(walk_run, name):
    """Wrong axes or scale put the feet tens of centimetres off; the reference model gives
    medians of about +0.5 cm and minima of -0.5 cm (walk) and -7 cm (run)."""
    clip = walk_run.clips[walk_run.clip_id(name)]
    assert abs(np.median(clip.foot_min_z)) <= 0.02
    assert clip.foot_min_z.min() >= -0.08


def test_walk_is_z_up_and_moves_forward(walk_run):
    clip = walk_run.clips[walk_run.clip_id("humanoid3d_walk")]
    head = clip.xpos[:, walk_run.character.head_body]
    assert (head[:, 2] > 1.3).all() and (head[:, 2] < 1.7).all()  # a 1.6 m character, upright
    assert clip.cycle_shift[0] > 1.0  # about 1.24 m along x per cycle


def test_mirroring_twice_is_the_identity(character):
    raw = load_raw(character, "humanoid3d_walk")
    np.testing.assert_array_equal(mirror_qpos(character, mirror_qpos(character, raw.qpos)), raw.qpos)


def test_mirrored_left_foot_is_the_reflected_right_foot(character, clip_cache):
    lib = MotionLibrary.load(character, ["humanoid3d_walk"], fps=30, mirror=True, cache_dir=clip_cache)
    orig, mirr = lib.clips
    assert mirr.name == "humanoid3d_walk_mirror"
    right = character.body_names.index("right_ankle")
    left = character.body_names.index("left_ankle")
    reflected = orig.xpos[:, right] * np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(mirr.xpos[:, left], reflected, atol=1e-9)


def test_finite_difference_velocities_integrate_back(character, walk_run):
    clip = walk_run.clips[walk_run.clip_id("humanoid3d_walk")]
    m = character.model
    # Generalised velocities are exact forward differences under MuJoCo's own integration.
    for t in range(clip.num_frames - 1):
        q = clip.qpos[t].copy()
        mujoco.mj_integratePos(m, q, clip.qvel[t], clip.dt)
        np.testing.assert_allclose(q, clip.qpos[t + 1], atol=1e-9)
    # The root's linear velocity is a pure translation rate: integrated, it gives the root path exactly.
    root = clip.xpos[0, 0] + np.cumsum(clip.lin_vel[:-1, 0] * clip.dt, axis=0)
    np.testing.assert_allclose(root, clip.xpos[1:, 0], atol=1e-9)
    # Other bodies also rotate, so one Euler step is off by O(dt²): measured 1.3 cm at most
    # (a swinging hand) against frame-to-frame displacements of up to 10.8 cm, median 0.14 mm.
    one_step = clip.xpos[:-1] + clip.lin_vel[:-1] * clip.dt
    err = np.linalg.norm(one_step - clip.xpos[1:], axis=-1)
    assert err.max() < 0.02 and np.median(err) < 0.001


def test_cyclic_clip_continues_across_the_loop(walk_run):
    cid = walk_run.clip_id("humanoid3d_walk")
    n = int(walk_run.num_frames[cid])
    s = walk_run.state(np.full(3, cid), np.array([n - 1, n, n + 1]))
    step = np.linalg.norm(np.diff(s.xpos[:, 0], axis=0), axis=-1)
    typical = np.linalg.norm(np.diff(walk_run.clips[cid].xpos[:, 0], axis=0), axis=-1).max()
    assert step.max() <= 1.5 * typical  # no jump back to the start
    # Frame n is frame 0 moved by one cycle, features included (they ignore heading and shift).
    s0 = walk_run.state(np.array([cid]), np.array([0]))
    np.testing.assert_allclose(walk_run.features([cid], [n]), walk_run.features([cid], [0]))
    assert s.xpos[1, 0, 0] == pytest.approx(s0.xpos[0, 0, 0] + walk_run.clips[cid].cycle_shift[0], abs=0.2)
    # Ten cycles on, the root has moved ten cycle shifts (closed-form power of the cycle transform).
    far = walk_run.state(np.array([cid]), np.array([10 * n]))
    manual = s0
    from workers.motion.library import transform_state

    clip = walk_run.clips[cid]
    for _ in range(10):
        manual = transform_state(manual, np.array([clip.cycle_yaw]), clip.cycle_shift[None])
    np.testing.assert_allclose(far.xpos, manual.xpos, atol=1e-9)
    head = walk_run.character.head_body
    np.testing.assert_allclose(walk_run.body_positions([cid], [10 * n], head), far.xpos[:, head], atol=1e-12)


def test_one_shot_clip_clamps_and_ends(character, clip_cache):
    lib = MotionLibrary.load(character, ["humanoid3d_kick"], fps=30, cache_dir=clip_cache)
    n = int(lib.num_frames[0])
    assert lib.is_last_frame(np.array([0, 0]), np.array([n - 2, n - 1])).tolist() == [False, True]
    np.testing.assert_array_equal(lib.state([0], [n + 5]).qpos, lib.state([0], [n - 1]).qpos)


def test_weighted_start_sampling(walk_run):
    walk_run = copy.deepcopy(walk_run)  # the session's library keeps its weights for later tests
    rng = np.random.default_rng(0)
    walk, run = walk_run.clip_id("humanoid3d_walk"), walk_run.clip_id("humanoid3d_run")
    walk_run.set_clip_weights([1.0 if i == run else 0.0 for i in range(walk_run.num_clips)])
    clips, frames = walk_run.sample_starts(500, rng)
    assert (clips == run).all() and (frames < walk_run.num_frames[run]).all()
    # ControlVAE balancing: frames with a low value are drawn more often.
    values = np.ones(walk_run.total_frames)
    hard = walk_run.offsets[walk] + 5
    values[hard] = 0.01  # weight 100 against 1
    walk_run.set_frame_weights(balancing_weights(values))
    clips, frames = walk_run.sample_starts(4000, rng)
    share = np.mean((clips == walk) & (frames == 5))
    expected = 100 / (100 + walk_run.total_frames - 1)
    assert share == pytest.approx(expected, rel=0.2)
    with pytest.raises(ValueError):
        walk_run.set_frame_weights(np.ones(3))


def test_cache_round_trip(character, tmp_path):
    fresh = load_clip(character, "humanoid3d_run", fps=30, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 1
    cached = load_clip(character, "humanoid3d_run", fps=30, cache_dir=tmp_path)
    for key, value in fresh.to_npz_dict().items():
        np.testing.assert_array_equal(np.asarray(getattr(cached, key)), value)
    # A corrupt cache entry is rebuilt, not fatal.
    next(tmp_path.glob("*.npz")).write_bytes(b"garbage")
    again = load_clip(character, "humanoid3d_run", fps=30, cache_dir=tmp_path)
    np.testing.assert_array_equal(again.xpos, fresh.xpos)


def test_resampling_to_another_rate(character):
    raw = load_raw(character, "humanoid3d_kick")  # one-shot: frames exactly 1 / fps apart
    c20 = process(character, raw, 20)
    c30 = process(character, raw, 30)
    assert c20.num_frames == int(raw.duration * 20) + 1
    # The same instant in both: t = 0.6 s is frame 12 at 20 Hz and frame 18 at 30 Hz.
    np.testing.assert_allclose(c20.xpos[12], c30.xpos[18], atol=0.01)


def test_npz_format_round_trip(character, tmp_path):
    from workers.motion.formats import npz

    raw = load_raw(character, "humanoid3d_jump")
    path = tmp_path / "jump.npz"
    npz.save(character, raw, path, fps=60)
    back = load_raw(character, path)
    np.testing.assert_array_equal(back.qpos, raw.qpos)
    assert back.loop and back.name == "jump"


def test_deepmimic_format_round_trip(character, tmp_path):
    from workers.motion.formats import deepmimic

    raw = load_raw(character, "walker/turn_left0")
    path = tmp_path / "turn.txt"
    deepmimic.save(character, raw, path)
    back = load_raw(character, path)
    np.testing.assert_allclose(back.qpos, raw.qpos, atol=1e-12)
    np.testing.assert_allclose(back.times, raw.times, atol=1e-12)
    assert back.loop == raw.loop


def test_pd_targets_are_the_reference_poses_targets_in_every_cycle(walk_run, character):
    # A cycle turns and moves only the root, so the joints' targets are looked up per stored frame.
    rng = np.random.default_rng(0)
    clips = rng.integers(0, walk_run.num_clips, 200)
    frames = rng.integers(0, 5 * walk_run.num_frames.max(), 200)  # looping clips wrap, one-shot ones hold
    want = character.qpos_to_action(walk_run.state(clips, frames).qpos).astype(np.float32)
    np.testing.assert_array_equal(walk_run.pd_targets(clips, frames), want)
