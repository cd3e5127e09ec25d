"""workers.sim.warp_sim.WarpSim (MuJoCo Warp, Warp's CPU device) against BatchedSim (MuJoCo C): the same resets
and actions give the same step results, falls, terminations; save and restore; the one-line refusals.

One WarpSim of four worlds is shared by the module (each test starts by resetting every world to fixed
reference states, which sets the whole physics state: time, controls and warm start included). Stepping
compiles MuJoCo Warp's kernels the first time on a machine (see test_warp_physics.py), hence `slow`.

Tolerances, from the comparison over three control steps (48 physics steps at 480 Hz, contacts with the
floor included), measured maxima in brackets: qpos and quaternions 1e-4 [9.2e-6], body positions 1e-4
[5e-7], velocities and state features 5e-3 [3.9e-4; body linear velocities 7e-6]. With one physics step
too many or too few per control step the differences were at least 3.4e-3 on positions and 12 on
velocities; with the PD targets off by 0.01 rad, 1e-2 and 1.2.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

pytest.importorskip("mujoco_warp")

from workers.body.features import amp_features, state_features  # noqa: E402
from workers.learners.base import Weights  # noqa: E402
from workers.learners.vae import ControlVAEObjective, VAEConfig, build_controller  # noqa: E402
from workers.models import device_features  # noqa: E402
from workers.motion.library import MotionLibrary  # noqa: E402
from workers.sim.env import BatchedSim, SimConfig, make_sim  # noqa: E402
from workers.sim.terrain import TerrainConfig  # noqa: E402
from workers.sim.warp_sim import WarpSim  # noqa: E402

N = 4
POS_TOL = 1e-4  # qpos, xpos, xquat (metres, radians, quaternion components)
VEL_TOL = 5e-3  # qvel, body linear and angular velocities; state features (heights, 6D rotations, velocities)
# A two-step head-error limit (ceil(0.05 s * 30 Hz) = 2), so that a tracking failure takes two control steps.
CONFIG = {"tracking_error_m": 0.5, "tracking_error_s": 0.05}
KIN_FIELDS = dict.fromkeys(("qpos", "xpos", "xquat"), POS_TOL) | dict.fromkeys(("qvel", "lin_vel", "ang_vel"), VEL_TOL)
WALK, KICK = 0, 1
DEVICE = os.environ.get("MOCAP_WARP_DEVICE", "cpu")  # scripts/device-warp.sh runs these on cuda


@pytest.fixture(scope="module")
def library(character, clip_cache):
    """A looping clip (walk) and a one-shot one (kick), for clip ends."""
    return MotionLibrary.load(character, ["humanoid3d_walk", "humanoid3d_kick"], fps=30, cache_dir=clip_cache)


@pytest.fixture(scope="module")
def warp(character, library):
    return make_sim(character, library, N, SimConfig(backend="warp", device=DEVICE, **CONFIG), seed=0)


@pytest.fixture(scope="module")
def mujoco_c(character, library):
    return make_sim(character, library, N, SimConfig(**CONFIG), seed=0)


def reset_both(sims, clips, frames):
    return [s.reset(np.arange(N), np.asarray(clips), np.asarray(frames)) for s in sims]


def tracking_actions(sim, rng, noise=0.1):
    """The reference's next PD targets plus noise (the same for both backends: computed from the bookkeeping)."""
    target = sim.library.state(sim.clip_id, sim.start_frame + sim.steps + 1).qpos
    return sim.character.qpos_to_action(target) + rng.normal(0.0, noise, (N, sim.action_dim))


def assert_kin_close(a, b, where):
    for name, tol in KIN_FIELDS.items():
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=tol, err_msg=f"{name}, {where}")


@pytest.mark.slow
def test_make_sim_builds_the_configured_backend(warp, mujoco_c):
    assert type(warp) is WarpSim and type(mujoco_c) is BatchedSim
    assert warp.physics.nworld == N and warp.physics.device.alias == ("cuda:0" if DEVICE == "cuda" else DEVICE)


@pytest.mark.slow
def test_steps_match_mujoco_c(warp, mujoco_c):
    sims = (warp, mujoco_c)
    states = reset_both(sims, [WALK, WALK, KICK, KICK], [5, 20, 3, 10])
    np.testing.assert_array_equal(states[0], states[1])  # the library's precomputed s
    assert_kin_close(warp.kin_state(), mujoco_c.kin_state(), "after the reset")
    rng = np.random.default_rng(0)
    for t in range(3):
        actions = tracking_actions(mujoco_c, rng)
        rw, rc = warp.step(actions), mujoco_c.step(actions)
        assert_kin_close(rw.kin, rc.kin, f"control step {t}")
        np.testing.assert_array_equal(rw.ref_state, rc.ref_state)
        np.testing.assert_allclose(rw.state, rc.state, rtol=0, atol=VEL_TOL)
        np.testing.assert_allclose(state_features(rw.kin), rc.state, rtol=0, atol=VEL_TOL)
        for flag in ("fell", "tracking_failed", "clip_ended", "timeout", "done"):
            np.testing.assert_array_equal(getattr(rw, flag), getattr(rc, flag), err_msg=flag)
        assert rw.kin.qpos.dtype == rc.kin.qpos.dtype == np.float64
    np.testing.assert_array_equal(warp.steps, 3)
    assert not warp.overflowed().any()
    # The bodies moved in those steps (a physics that did nothing could not stay within POS_TOL of MuJoCo C).
    assert np.abs(warp.kin_state().xpos - warp.library.state(warp.clip_id, warp.start_frame).xpos).max() > 0.05


@pytest.mark.slow
def test_what_a_step_reports_is_made_on_the_device(warp):
    """The body states, the KinState and s of a step are computed where the worlds live and copied once:
    the same numbers, to float32 rounding, as the host's computation from the physics arrays (each body
    origin's velocity v + w x r in float64, then packed; s in NumPy); the KinState is the body states widened."""
    from workers.models.body_state import pack

    reset_both([warp], [WALK, WALK, KICK, KICK], [5, 20, 3, 10])
    np.testing.assert_array_equal(warp.body_states(), pack(warp.kin_state()))
    np.testing.assert_array_equal(warp.body_states(np.array([2, 0])), warp.body_states()[[2, 0]])
    r = warp.step(tracking_actions(warp, np.random.default_rng(2)))
    assert r.packed is not None and r.features is not None  # the backend's, not derived on the host
    assert "kin" not in vars(r)  # the KinState's host copies are made when read, not every step
    assert r.body_states.dtype == np.float32 and r.body_states.shape == (N, warp.character.num_bodies, 13)
    np.testing.assert_array_equal(r.body_states, pack(r.kin))
    a = warp._arrays()  # float64 copies of the device arrays
    w, r_com = a.cvel[:, 1:, :3], a.xpos[:, 1:] - a.subtree_com[:, 1:2]
    lin = a.cvel[:, 1:, 3:] + np.cross(w, r_com)
    assert np.abs(lin).max() > 0.1  # moving bodies: a wrong sign or order of the cross product would show
    np.testing.assert_allclose(r.kin.lin_vel, lin, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(r.kin.qpos, a.qpos)
    np.testing.assert_array_equal(r.kin.xquat, a.xquat[:, 1:])
    np.testing.assert_allclose(r.state, state_features(r.kin), rtol=0, atol=1e-5)
    assert r.state.dtype == np.float32
    # The state on the device, which the recorders read there: the step's, not the worlds' live arrays.
    on = r.on_device
    np.testing.assert_array_equal(on.qpos.cpu().numpy(), r.kin.qpos)
    np.testing.assert_array_equal(on.body_states.cpu().numpy(), r.body_states)
    phi = device_features.amp_features(warp.character, on).cpu().numpy()
    np.testing.assert_allclose(phi, amp_features(warp.character, r.kin), rtol=0, atol=2e-5)
    warp.step(tracking_actions(warp, np.random.default_rng(3)))
    np.testing.assert_array_equal(on.qpos.cpu().numpy(), r.kin.qpos)
    np.testing.assert_array_equal(warp.device_state().body_states.cpu().numpy(), warp.body_states())


@pytest.mark.slow
def test_falls_on_the_same_control_step(warp, mujoco_c):
    """Pushed sideways or forwards (2-3 m/s at the root) while holding the start pose, or with the servos
    pulling every joint to zero: every character falls within 30 control steps, on the same step on both
    (measured: control steps 15, 16, 14 and 26)."""
    clips, frames = [WALK, KICK, WALK, WALK], [5, 10, 20, 8]
    pushes = np.array([[2.0, 0, 0], [0, 2.0, 0], [0, -3.0, 0], [0, 0, 0]])
    first = []
    for sim in (warp, mujoco_c):
        reset_both([sim], clips, frames)
        ref = sim.library.state(np.array(clips), np.array(frames))
        qvel = ref.qvel.copy()
        qvel[:, :3] += pushes
        sim.set_state(np.arange(N), ref.qpos, qvel)
        hold = sim.character.qpos_to_action(ref.qpos)
        hold[3] = 0.0
        fell_at = np.full(N, -1)
        for t in range(30):
            fell = sim.step(hold).fell
            if sim is warp:  # found on the device: the same as from the contact pool's rows on the host
                world, geom = warp.physics.contacts()
                np.testing.assert_array_equal(fell, np.isin(np.arange(N), world[warp._fall_geom[geom].any(axis=1)]))
            fell_at[fell & (fell_at < 0)] = t
            if (fell_at >= 0).all():
                break
        first.append(fell_at)
    assert (first[1] >= 5).all()  # falls, not contacts of the start
    np.testing.assert_array_equal(first[0], first[1])


@pytest.mark.slow
def test_partial_reset_switch_tracking_failure_and_clip_end(warp, mujoco_c):
    """The reference bookkeeping (shared code) on MuJoCo Warp, step by step as on MuJoCo C."""
    kick_frames = int(warp.library.num_frames[KICK])
    sims = (warp, mujoco_c)
    reset_both(sims, [WALK] * N, [5, 10, 15, 20])
    hold = [s.character.qpos_to_action(s.kin_state().qpos) for s in sims]
    for s, a in zip(sims, hold, strict=True):
        s.step(a)
    before = warp.kin_state()
    # Reset two environments only: a kick frame two before its end, and a walk frame.
    ids, clips, frames = np.array([2, 0]), np.array([KICK, WALK]), np.array([kick_frames - 3, 8])
    states = [s.reset(ids, clips, frames) for s in sims]
    np.testing.assert_array_equal(states[0], warp.library.features(clips, frames))
    np.testing.assert_array_equal(states[0], states[1])
    after = warp.kin_state()
    np.testing.assert_array_equal(after.qpos[[1, 3]], before.qpos[[1, 3]])  # the others untouched
    ref = warp.library.state(clips, frames)
    np.testing.assert_allclose(after.qpos[ids], ref.qpos, rtol=0, atol=1e-6)  # float32 of the reference
    np.testing.assert_array_equal(warp.steps, [0, 1, 0, 1])
    # A new reference 26 frames ahead for environment 1 (its frame 11 -> 37): the reference's head is 0.9 m ahead.
    far = int(warp.library.num_frames[WALK]) - 1
    for s in sims:
        s.switch_reference(np.array([1]), np.array([WALK]), np.array([far]))
    np.testing.assert_array_equal(warp.start_frame[1] + warp.steps[1], far)
    flags = []
    for _ in range(2):
        results = [s.step(a) for s, a in zip(sims, hold, strict=True)]
        for name in ("tracking_failed", "clip_ended", "done"):
            np.testing.assert_array_equal(getattr(results[0], name), getattr(results[1], name), err_msg=name)
        flags.append((results[0].tracking_failed.tolist(), results[0].clip_ended.tolist()))
    # Two steps of head error end environment 1; the kick runs out after two steps (frames n-2, n-1).
    assert flags == [([False] * 4, [False] * 4), ([False, True, False, False], [False, False, True, False])]


@pytest.mark.slow
def test_save_and_restore_continue_the_same_trajectory(warp):
    reset_both([warp], [WALK, WALK, KICK, KICK], [5, 20, 3, 10])
    rng = np.random.default_rng(1)
    warp.step(tracking_actions(warp, rng))
    saved = warp.save_state()
    assert saved["qacc_warmstart"].shape == (N, warp.model.nv) and np.abs(saved["qacc_warmstart"]).max() > 0
    actions = [tracking_actions(warp, rng) for _ in range(2)]
    first = [warp.step(a) for a in actions]
    # Somewhere else entirely, then back.
    reset_both([warp], [KICK] * N, [0, 1, 2, 3])
    warp.switch_reference(np.array([0]), np.array([WALK]), np.array([3]))
    warp.restore_state(saved)
    np.testing.assert_array_equal(warp.qacc_warmstart, saved["qacc_warmstart"])
    second = [warp.step(a) for a in actions]
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a.kin.qpos, b.kin.qpos)
        np.testing.assert_array_equal(a.kin.lin_vel, b.kin.lin_vel)
        np.testing.assert_array_equal(a.ref_state, b.ref_state)
        np.testing.assert_array_equal(a.done, b.done)
    np.testing.assert_array_equal(warp.steps, saved["steps"] + 2)
    with pytest.raises(ValueError, match="for 2 environments"):
        warp.restore_state({k: v[:2] for k, v in saved.items()})


@pytest.mark.slow
def test_the_rewards_recorded_on_the_device_are_numpys(warp, character, library):
    """The tracker's imitation reward from the step's state on the device against the reference looked up there,
    and ControlVAE's tracking reward in a worker (its first state, every step's, and resets'), agree with
    the NumPy recorders' to float32 rounding."""
    from workers.learners.vae import state_weight_vector
    from workers.models.body_state import features_np
    from workers.policies import VAEPolicy
    from workers.recorders import ImitationReward, TrackingReward
    from workers.rewards import imitation_reward, tracking_reward
    from workers.rollout import RolloutWorker

    reset_both([warp], [WALK, WALK, KICK, KICK], [5, 20, 3, 10])
    r = warp.step(tracking_actions(warp, np.random.default_rng(4), noise=0.3))
    weights = {"pose": 0.2, "velocity": 0.01, "end_effector": 4.0, "root": 1.0}
    rec = ImitationReward(character, weights)
    rec.begin(1, N, warp)
    rec.record(0, warp, r)  # on the device, from the step's state there
    on = rec.finish()
    reward, terms = imitation_reward(character, r.kin, warp.reference_state(), weights)  # NumPy's, on the host
    assert np.ptp(reward) > 1e-3
    for key, value in {"reward": reward, **{f"reward/{k}": v for k, v in terms.items()}}.items():
        assert on[key].shape == (1, N), key
        np.testing.assert_allclose(on[key][0], value, rtol=0, atol=1e-4, err_msg=key)

    weights = state_weight_vector(character.num_bodies, ControlVAEObjective().state_weights).numpy()
    vae = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(64,))
    policy = VAEPolicy(character.num_bodies, character.num_actions, vae, 0.5)
    config = SimConfig(backend="warp", device=DEVICE, max_episode_steps=3)
    worker = RolloutWorker(character, library, 3, policy, config, seed=2, recorders=[TrackingReward(weights)])
    torch.manual_seed(0)
    worker.set_weights(Weights(1, build_controller(character.num_bodies, character.num_actions, vae).state_dict()))
    traj = worker.collect(5)
    assert traj.done[2].all()
    s = features_np(traj.states.reshape(15, *traj.states.shape[2:])).reshape(5, 3, -1)
    want = tracking_reward(s, library.features(traj.clip_id, traj.frame), weights)
    assert want.min() < 0.9 and want[0].min() > 0.99  # from the references' own states, then away from them
    np.testing.assert_allclose(traj.extras["reward"], want, rtol=0, atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize(
    "field, index, value, warning, tol",
    [
        ("qvel", 7, np.nan, "BADQVEL", POS_TOL),
        ("qpos", 9, np.nan, "BADQPOS", POS_TOL),  # a ball joint's quaternion: MuJoCo Warp would normalise it
        ("qvel", 7, 1e6, "BADQACC", 5e-3),  # found after the physics step's integration: a step behind
    ],
)
def test_an_unstable_world_is_reset_and_counted_as_mujoco_c_does(warp, mujoco_c, field, index, value, warning, tol):
    """A non-finite or huge value resets the world to the model's qpos0 at rest, with zero controls, and counts
    MuJoCo's warning, as MuJoCo C does: the same warning counts and, a control step later, the same state. A
    reset for the accelerations lags MuJoCo C's by one physics step (1/480 s), hence its wider tolerance."""
    import mujoco

    states = []
    for sim in (mujoco_c, warp):
        reset_both([sim], [WALK] * N, [5, 10, 15, 20])
        kin = sim.kin_state()
        bad = {"qpos": kin.qpos.copy(), "qvel": kin.qvel.copy()}
        bad[field][2, index] = value
        sim.set_state(np.arange(N), bad["qpos"], bad["qvel"])
        r = sim.step(sim.character.qpos_to_action(kin.qpos))
        r = sim.step(sim.character.qpos_to_action(kin.qpos))
        assert np.isfinite(r.kin.qpos).all() and np.isfinite(r.kin.qvel).all()
        counts = {
            w: sim.warning_counts(getattr(mujoco.mjtWarning, f"mjWARN_{w}")) for w in ("BADQPOS", "BADQVEL", "BADQACC")
        }
        assert counts[warning][2] == 1 and sum(c.sum() for c in counts.values()) == 1, (type(sim).__name__, counts)
        states.append(r.kin)
    c, w = states
    assert np.abs(c.qpos[2] - warp.model.qpos0).max() > 1e-2  # moved on from qpos0 after the reset
    np.testing.assert_allclose(w.qpos, c.qpos, rtol=0, atol=tol)
    np.testing.assert_allclose(w.qvel[[0, 1, 3]], c.qvel[[0, 1, 3]], rtol=0, atol=VEL_TOL)  # the others untouched
    # Lagging by a physics step, the reset world's joint velocities differ by up to 0.17 rad/s two control steps on.
    np.testing.assert_allclose(w.qvel[2], c.qvel[2], rtol=0, atol=VEL_TOL if tol == POS_TOL else 0.25)


def test_bad_device_is_refused_in_one_line():
    for device in ("gpu", "cuda:x", "CPU", 0):
        with pytest.raises(ValueError, match="sim device must be 'cpu', 'cuda' or 'cuda:N'") as e:
            SimConfig(backend="warp", device=device)
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="needs sim backend 'warp'"):
        SimConfig(device="cuda")
    assert SimConfig(backend="warp", device="cuda:1").device == "cuda:1"  # checked when a WarpSim is made


def test_rough_terrain_is_refused_on_warp_in_one_line(character, library):
    config = SimConfig(backend="warp", terrain=TerrainConfig(kind="rough"))
    with pytest.raises(NotImplementedError, match="terrain.kind='rough'.*sim backend 'warp'") as e:
        WarpSim(character, library, 1, config)
    assert "\n" not in str(e.value) and "4 contacts per geom pair" in str(e.value)


def test_warp_sim_refuses_a_mujoco_config(character, library):
    with pytest.raises(ValueError, match="WarpSim runs sim backend 'warp', the config says 'mujoco'"):
        WarpSim(character, library, 1, SimConfig())
