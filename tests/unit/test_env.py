"""The batched simulator: reset, step, terminations, determinism."""

from dataclasses import replace

import mujoco
import numpy as np
import pytest

from workers.sim.env import BatchedSim, SimConfig, without_tracking_termination


def test_reset_is_reference_state_initialisation(character, walk_run):
    sim = BatchedSim(character, walk_run, num_envs=6, seed=0)
    states = sim.reset()
    np.testing.assert_allclose(states, walk_run.features(sim.clip_id, sim.start_frame), atol=1e-5)
    np.testing.assert_allclose(sim.kin_state().qpos, walk_run.state(sim.clip_id, sim.start_frame).qpos)


def test_step_shapes_and_reference(character, walk_run):
    sim = BatchedSim(character, walk_run, num_envs=4, seed=1)
    ref = sim.reference_state()
    r = sim.step(character.qpos_to_action(ref.qpos))
    assert r.state.shape == (4, sim.state_dim) == r.ref_state.shape
    assert r.done.shape == (4,) and r.done.dtype == bool
    np.testing.assert_array_equal(sim.steps, 1)
    # The reference advanced one frame and the character followed it closely.
    np.testing.assert_allclose(r.ref_state, walk_run.features(sim.clip_id, sim.start_frame + 1), atol=1e-5)
    err = np.linalg.norm(r.kin.xpos - sim.reference_state().xpos, axis=-1).max()
    assert err < 0.1
    with pytest.raises(ValueError, match="actions must be"):
        sim.step(np.zeros((3, 28)))


def test_falls_are_detected(character, walk_run):
    sim = BatchedSim(character, walk_run, num_envs=2, config=SimConfig(tracking_error_m=0), seed=0)
    # Servos holding the zero pose from mid-stride: without balance the character topples.
    fell_at = None
    for t in range(90):
        r = sim.step(np.zeros((2, 28)))
        if r.fell.all():
            fell_at = t
            break
    assert fell_at is not None and fell_at < 90
    # Lying on the ground means a low root.
    assert sim.kin_state().xpos[:, 0, 2].max() < 0.6
    # ControlVAE's collection: a fall is reported but does not end the episode.
    lying = BatchedSim(character, walk_run, 2, SimConfig(tracking_error_m=0, end_on_fall=False), seed=0)
    results = [lying.step(np.zeros((2, 28))) for _ in range(fell_at + 1)]
    assert results[-1].fell.all() and not any(r.done.any() for r in results)


def test_tracking_failure_after_one_second(character, walk_run):
    config = SimConfig(allowed_contacts=(), tracking_error_m=0.5, tracking_error_s=1.0)
    sim = BatchedSim(character, walk_run, num_envs=1, config=config, seed=0)
    hold = character.qpos_to_action(sim.kin_state().qpos)
    failed = []
    for _ in range(120):
        r = sim.step(hold)  # stands in place while the reference walks away
        failed.append(bool(r.tracking_failed[0]))
    first = failed.index(True)
    # Head 0.5 m behind after ~0.4 s of walking at ~1.2 m/s, then held for 1 s (30 steps).
    assert 30 <= first <= 90


def test_clip_end_for_one_shot_clips(character, clip_cache):
    from workers.motion.library import MotionLibrary

    lib = MotionLibrary.load(character, ["humanoid3d_kick"], fps=30, cache_dir=clip_cache)
    config = SimConfig(allowed_contacts=(), tracking_error_m=0)
    sim = BatchedSim(character, lib, num_envs=1, config=config, seed=0)
    n = int(lib.num_frames[0])
    sim.reset(np.array([0]), np.array([0]), np.array([n - 3]))
    ended = [bool(sim.step(np.zeros((1, 28))).clip_ended[0]) for _ in range(2)]
    assert ended == [False, True]


def test_same_seed_same_trajectory(character, walk_run):
    def run():
        sim = BatchedSim(character, walk_run, num_envs=3, seed=42)
        rng = np.random.default_rng(0)
        out = []
        for _ in range(10):
            out.append(sim.step(rng.normal(0, 0.2, (3, 28))).state)
        return np.stack(out)

    np.testing.assert_array_equal(run(), run())


def test_bad_rates_are_refused(character, walk_run):
    with pytest.raises(ValueError, match="whole multiple"):
        BatchedSim(character, walk_run, 1, SimConfig(sim_hz=100, control_hz=30))
    with pytest.raises(ValueError, match="library sampled"):
        BatchedSim(character, walk_run, 1, SimConfig(sim_hz=480, control_hz=60))
    with pytest.raises(ValueError, match="num_envs"):
        BatchedSim(character, walk_run, 0)


def test_batch_matches_a_loop_over_mjdata(character, walk_run):
    """mujoco.batch steps exactly as the per-MjData loop it replaced: states, warm starts, falls."""
    config = SimConfig(sim_hz=120, control_hz=30)
    sim = BatchedSim(character, walk_run, num_envs=4, config=config, seed=0)
    m, k = sim.model, sim.substeps
    ref = sim.reference_state()
    datas = [mujoco.MjData(m) for _ in range(4)]
    for d, q, v in zip(datas, ref.qpos, ref.qvel, strict=True):
        d.qpos[:], d.qvel[:] = q, v
        mujoco.mj_forward(m, d)
    rng = np.random.default_rng(0)
    for _ in range(40):  # long enough to fall: contacts, the fall test and the solver's warm start
        actions = rng.normal(0, 0.3, (4, 28))
        r = sim.step(actions)
        for d, a in zip(datas, actions, strict=True):
            d.ctrl[:] = a
            mujoco.mj_step2(m, d)
            mujoco.mj_step(m, d, nstep=k - 1)
            mujoco.mj_step1(m, d)
        np.testing.assert_array_equal(r.kin.qpos, np.stack([d.qpos for d in datas]))
        np.testing.assert_array_equal(r.kin.xpos, np.stack([d.xpos[1:] for d in datas]))
        np.testing.assert_array_equal(sim.qacc_warmstart, np.stack([d.qacc_warmstart for d in datas]))
        fell = [d.ncon > 0 and bool(sim._fall_geom[d.contact.geom].any()) for d in datas]
        np.testing.assert_array_equal(r.fell, fell)


def test_without_tracking_termination_keeps_everything_else():
    base = SimConfig(control_hz=20.0, sim_hz=120.0, tracking_error_m=0.3, max_episode_steps=50, end_on_fall=False)
    evaluation = without_tracking_termination(base)
    assert evaluation == replace(base, tracking_error_m=0.0, max_episode_steps=0)
    assert without_tracking_termination(base, keep_time_limit=True) == replace(base, tracking_error_m=0.0)
    assert without_tracking_termination() == replace(SimConfig(), tracking_error_m=0.0, max_episode_steps=0)
    assert base.tracking_error_m == 0.3 and base.max_episode_steps == 50  # the given config is left as it was


def test_reference_next_features_is_the_library_one_frame_ahead(character, walk_run):
    sim = BatchedSim(character, walk_run, num_envs=4, seed=2)
    sim.step(character.qpos_to_action(sim.reference_state().qpos))
    expected = walk_run.features(sim.clip_id, sim.start_frame + sim.steps + 1)
    np.testing.assert_array_equal(sim.reference_next_features(), expected)
    ids = np.array([3, 1])
    np.testing.assert_array_equal(sim.reference_next_features(ids), expected[ids])
