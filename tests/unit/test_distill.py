"""PULSE's distillation helpers: the teacher's labels of stored states, and the imitation success metrics."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from workers.distill import teacher_actions
from workers.evaluation.imitation import reference_actor
from workers.evaluation.success import tracking_steps, tracking_success
from workers.learners.ppo import PPOConfig, build_actor_critic
from workers.models import body_state
from workers.policies import GaussianPolicy, observation_dim
from workers.sim.env import BatchedSim

SMALL = PPOConfig(policy_hidden=(32,), value_hidden=(32,), policy_out_scale=1.0)
GRAVITY_DROP_MM = 1000 * 0.5 * 9.81 * (1 / 30) ** 2  # free fall for one control step: 5.45 mm


def zero_targets(sim, bs):
    """PD targets of all zeros: the servos pull the character into its zero pose and it topples."""
    return np.zeros((sim.num_envs, sim.action_dim))


def hold(library):
    """Before each step, put every character at rest on the reference's next pose and aim at that pose:
    the step then ends on the reference up to what gravity and the servos move in 1/30 s."""
    pd = reference_actor(library)

    def act(sim, bs):
        ref = library.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        sim.set_state(np.arange(sim.num_envs), ref.qpos, np.zeros_like(ref.qvel))
        return pd(sim, bs)

    return act


@pytest.mark.parametrize("observation", ["imitation", "mimic"])
def test_teacher_actions_equal_the_policys_mean_action_in_one_batch(character, walk_run, observation):
    torch.manual_seed(0)
    sim = BatchedSim(character, walk_run, 4, seed=1)  # random reference starts on both clips
    module = build_actor_critic(observation_dim(observation, sim.state_dim), sim.action_dim, SMALL)
    module.obs_norm.update(torch.randn(64, module.obs_dim) * 3 + 1)  # a non-trivial normaliser
    residual = GaussianPolicy(module, observation, residual=True)
    plain = GaussianPolicy(module, observation, residual=False)
    states, clips, frames, want, want_plain = [], [], [], [], []
    bs = body_state.pack(sim.kin_state())
    for _ in range(5):  # the closed loop visits states off the reference
        states.append(bs)
        clips.append(sim.clip_id.copy())
        frames.append(sim.start_frame + sim.steps)
        want.append(residual.mean_action(sim, bs))
        want_plain.append(plain.mean_action(sim, bs))
        bs = body_state.pack(sim.step(want[-1]).kin)
    states, clips, frames = np.concatenate(states), np.concatenate(clips), np.concatenate(frames)
    module.train()
    got = teacher_actions(module, character, walk_run, states, clips, frames, observation=observation)
    assert got.shape == (20, sim.action_dim) and got.dtype == np.float32
    np.testing.assert_allclose(got, np.concatenate(want), atol=1e-5)
    got_plain = teacher_actions(module, character, walk_run, states, clips, frames, False, observation)
    np.testing.assert_allclose(got_plain, np.concatenate(want_plain), atol=1e-5)
    assert np.abs(got - got_plain).max() > 0.1  # the residual base is really added
    assert module.training  # the module's mode is restored
    # One clip and frame for all rows broadcast.
    one = teacher_actions(module, character, walk_run, states[:1], int(clips[0]), int(frames[0]), True, observation)
    np.testing.assert_allclose(one, got[:1], atol=1e-6)
    with pytest.raises(ValueError, match="body states"):
        teacher_actions(module, character, walk_run, states[0], clips[0], frames[0])


def test_tracking_steps_by_hand():
    lib = SimpleNamespace(loop=np.array([True, False, False]), num_frames=np.array([38, 24, 1]))
    # A cycle of a looping clip; a one-shot clip up to its last frame (and at least one step).
    np.testing.assert_array_equal(tracking_steps(lib, 30.0), [38, 23, 1])
    np.testing.assert_array_equal(tracking_steps(lib, 30.0, seconds=2.0), [60, 23, 1])
    np.testing.assert_array_equal(tracking_steps(lib, 30.0, seconds=0.5), [15, 15, 1])
    with pytest.raises(ValueError, match="positive"):
        tracking_steps(lib, 30.0, seconds=0.0)


def test_tracking_success_of_an_oracle_is_one_and_its_error_one_step_of_free_fall(character, walk_run):
    out = tracking_success(hold(walk_run), character, walk_run)
    assert set(out["per_clip"]) == {"humanoid3d_walk", "humanoid3d_run"}
    assert out["success_rate_every_joint"] == 1.0 and out["success_rate_pulse"] == 1.0
    # Each step starts at rest on the reference: the body sinks by about ½ g dt² (measured 5.45, 5.48 mm)
    # and hardly changes shape (root-relative: measured 0.2 and 1.5 mm).
    for clip in out["per_clip"].values():
        assert clip["success_every_joint"] and clip["mpjpe_mm"] == pytest.approx(GRAVITY_DROP_MM, abs=0.5)
        assert clip["mpjpe_local_mm"] < 3.0 and clip["max_error_m"] < 0.03
    per_clip_mean = np.mean([c["mpjpe_mm"] for c in out["per_clip"].values()])
    assert out["mpjpe_mm"] == pytest.approx(per_clip_mean)


def test_tracking_success_of_pd_tracking_and_of_zero_targets(character, walk_run):
    pd = tracking_success(reference_actor(walk_run), character, walk_run)
    assert set(pd["per_clip"]) == set(walk_run.names)
    # Open-loop PD tracking keeps no balance and falls within the clip (walk: 38 steps, measured
    # 364 mm global, 235 mm root-relative; run: 24 steps, 643 and 387 mm).
    walk = pd["per_clip"]["humanoid3d_walk"]
    assert 0.0 < walk["mpjpe_mm"] < 500.0 and 0.0 < pd["mpjpe_local_mm"] < 500.0
    # Zero PD targets topple the character: every clip fails by either rule, with larger errors.
    zero = tracking_success(zero_targets, character, walk_run)
    assert zero["success_rate_every_joint"] == 0.0 and zero["success_rate_pulse"] == 0.0
    for name in walk_run.names:
        assert not zero["per_clip"][name]["success_pulse"]
        assert zero["per_clip"][name]["mpjpe_mm"] > pd["per_clip"][name]["mpjpe_mm"]
    assert zero["mpjpe_mm"] > pd["mpjpe_mm"]
    # No error is 100 m: every clip succeeds.
    assert tracking_success(zero_targets, character, walk_run, threshold=100.0)["success_rate_pulse"] == 1.0
    assert zero == tracking_success(zero_targets, character, walk_run)  # deterministic


def test_every_joint_rule_is_stricter_than_the_mean_joint_rule(character, walk_run):
    # Over the first 6 steps (0.2 s) PD tracking of the walk stays within 0.15 m at every joint
    # (measured max 0.144 m) with a mean over joints of at most 0.061 m: under a 0.1 m threshold the
    # walk fails the every-joint rule and passes PULSE's mean-joint rule.
    out = tracking_success(reference_actor(walk_run), character, walk_run, seconds=0.2, threshold=0.1)
    walk = out["per_clip"]["humanoid3d_walk"]
    assert 0.1 < walk["max_error_m"] < 0.15
    assert not walk["success_every_joint"] and walk["success_pulse"]
    default = tracking_success(reference_actor(walk_run), character, walk_run, seconds=0.2)
    assert default["per_clip"]["humanoid3d_walk"]["success_every_joint"]  # 0.144 m <= 0.5 m


@pytest.mark.parametrize("observation", ["imitation", "mimic"])
def test_the_pulse_learner_labels_each_window_state_at_its_own_frame(character, walk_run, observation):
    """PulseActor.batch: window state t, stored at reference frame `frame + t` (as the rollout records it,
    sim.start_frame + sim.steps before the step), is labelled with the teacher's action there, the
    action GaussianPolicy.mean_action gave in the simulator; a label one frame off fails."""
    from orchestrator.components.pulse import PulseActor
    from workers.types import WindowBatch

    torch.manual_seed(0)
    sim = BatchedSim(character, walk_run, 3, seed=2)
    module = build_actor_critic(observation_dim(observation, sim.state_dim), sim.action_dim, SMALL)
    policy = GaussianPolicy(module, observation, residual=True)
    first_clip, first_frame = sim.clip_id.copy(), sim.start_frame + sim.steps
    states, want = [body_state.pack(sim.kin_state())], []
    for _ in range(6):
        want.append(policy.mean_action(sim, states[-1]))
        states.append(body_state.pack(sim.step(want[-1]).kin))
    assert (sim.steps == 6).all()  # no episode restarted inside the window
    actor = PulseActor.__new__(PulseActor)
    actor.character, actor.library, actor.teacher, actor.residual = character, walk_run, module, True
    actor.observation = observation
    window = WindowBatch(np.stack(states, 1), np.stack(want, 1), first_clip, first_frame, np.zeros(3, int))
    batch = actor.batch(window)
    np.testing.assert_allclose(batch.actions, np.stack(want, 1), atol=1e-5)
    want_ref = walk_run.state(np.repeat(first_clip, 7), (first_frame[:, None] + np.arange(7)).ravel())
    np.testing.assert_allclose(batch.reference, body_state.pack(want_ref).reshape(3, 7, 15, 13), atol=1e-5)
    shifted = WindowBatch(window.states, window.actions, first_clip, first_frame + 1, window.version)
    assert np.abs(actor.batch(shifted).actions - np.stack(want, 1)).max() > 1e-2
