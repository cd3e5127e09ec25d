"""Evaluation protocols: time-until-fall (PhysicsVAE) and tracking error (ControlVAE), at small settings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from workers.body.features import relative_position_error
from workers.evaluation.controller import (
    fall_start,
    random_sampling,
    reference_targets,
    time_until_fall,
    tracking_error,
    tracking_segments,
)
from workers.learners.vae import VAEConfig, build_controller
from workers.motion.library import MotionLibrary

SMALL = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(64,))
DT = 1 / 30


def controller(character, seed=0, out_gain=1.0):
    """A small untrained controller; out_gain scales its output layer (the default init is near zero)."""
    torch.manual_seed(seed)
    c = build_controller(character.num_bodies, character.num_actions, SMALL)
    with torch.no_grad():
        c.policy.net.out.weight.mul_(out_gain)
    return c


def test_relative_position_error_by_hand():
    ref = np.random.default_rng(0).normal(size=(2, 5, 3))
    assert np.allclose(relative_position_error(ref, ref), 0.0)
    # A rigid translation of the whole body changes no position relative to the root.
    assert np.allclose(relative_position_error(ref + np.array([1.0, -2.0, 0.5]), ref), 0.0)
    # Moving one non-root body by (0.3, 0.4, 0) is an error of 0.5 m on 1 of the 4 non-root bodies.
    moved = ref.copy()
    moved[:, 2] += [0.3, 0.4, 0.0]
    np.testing.assert_allclose(relative_position_error(moved, ref), [0.125, 0.125])
    # Moving the root alone by 0.1 m moves every other body by 0.1 m relative to it.
    moved = ref.copy()
    moved[:, 0] += [0.0, 0.0, 0.1]
    np.testing.assert_allclose(relative_position_error(moved, ref), [0.1, 0.1])


def test_time_until_fall_of_an_untrained_controller(character, walk_run):
    c = controller(character)
    out = time_until_fall(c, character, walk_run, num_rollouts=8, max_seconds=5.0)
    times = np.array(out["times"])
    assert len(times) == 8
    assert np.isfinite(times).all() and (times > 0).all() and (times <= 5.0).all()
    # A rollout ends on a control step: times are whole steps.
    np.testing.assert_allclose(times / DT, np.round(times / DT), atol=1e-9)
    assert out["mean"] == pytest.approx(times.mean()) and out["median"] == pytest.approx(np.median(times))
    assert out["fallen"] == 1.0  # near-zero PD targets (a stiff T-pose) topple it within the 5 s
    again = time_until_fall(c, character, walk_run, num_rollouts=8, max_seconds=5.0)
    assert again == out  # deterministic for a seed
    # A cap before the first fall: every rollout counts as the cap and none as fallen.
    capped = time_until_fall(c, character, walk_run, num_rollouts=4, max_seconds=0.2)
    assert capped["times"] == [0.2] * 4 and capped["fallen"] == 0.0
    assert c.training  # the controller's mode is restored


def test_time_until_fall_has_one_start_and_samples_z_per_rollout(character, walk_run):
    """All rollouts start from the same state: a policy that ignores z falls at the same step in every
    rollout; one that depends strongly on z (output layer scaled up) falls at different times."""
    blind = controller(character)
    with torch.no_grad():
        blind.policy.net.out.weight.zero_()  # a = bias = 0 for every s and z
    out = time_until_fall(blind, character, walk_run, num_rollouts=6, max_seconds=5.0, start=("humanoid3d_run", 3))
    assert len(set(out["times"])) == 1 and out["std"] == pytest.approx(0.0, abs=1e-12)
    sensitive = controller(character, out_gain=100.0)
    out = time_until_fall(sensitive, character, walk_run, num_rollouts=6, max_seconds=5.0)
    assert len(set(out["times"])) > 1
    assert fall_start(walk_run) == (walk_run.clip_id("humanoid3d_walk"), 0)
    with pytest.raises(KeyError, match="no clip 'nope'"):
        fall_start(walk_run, ("nope", 0))
    with pytest.raises(ValueError, match="outside clip"):
        fall_start(walk_run, ("humanoid3d_walk", 1000))


def test_time_until_fall_draws_a_fresh_standard_normal_z_every_control_step(character, walk_run):
    """PhysicsVAE's protocol: z ~ N(0, I) at every control step of every rollout. The latents the policy
    is given (recorded) must pass a Kolmogorov-Smirnov test against N(0, 1) in every dimension, have an
    identity covariance and no correlation between consecutive steps: a z drawn once per rollout (lag-1
    correlation 1), a prior's mean (variance 0) or a wrong scale fails."""
    from scipy import stats

    c = build_controller(
        character.num_bodies,
        character.num_actions,
        dataclasses.replace(SMALL, prior="standard_normal", objective="physicsvae"),
    )
    seen = []
    act = c.act

    def recording(s, z):
        seen.append(z.detach().clone())
        return act(s, z)

    c.act = recording
    time_until_fall(c, character, walk_run, num_rollouts=16, max_seconds=2.0)
    z = torch.stack(seen).numpy()  # [steps, rollouts, 8]
    assert z.shape[1:] == (16, 8) and z.shape[0] >= 10
    flat = z.reshape(-1, 8)
    for d in range(8):
        assert stats.kstest(flat[:, d], "norm").pvalue > 1e-3, d
    cov = np.cov(flat, rowvar=False)
    assert np.abs(cov - np.eye(8)).max() < 0.25
    lag1 = np.mean([np.corrcoef(z[:-1, r, d], z[1:, r, d])[0, 1] for r in range(16) for d in range(8)])
    assert abs(lag1) < 0.1


def test_tracking_error_of_the_reference_is_small_and_of_an_untrained_controller_large(character, walk_run):
    pd = reference_targets(walk_run)

    def hold(sim):
        """Before each step, put every character at rest on the reference's *next* pose and aim at that pose:
        the step then ends on the reference up to what gravity and the PD servos move in 1/30 s (measured:
        walk 0.2 mm, run 1.4 mm). Comparing with the reference one frame off would give 16 and 51 mm."""
        ref = walk_run.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        sim.set_state(np.arange(sim.num_envs), ref.qpos, np.zeros_like(ref.qvel))
        return pd(sim)

    near = tracking_error(None, character, walk_run, clip_seconds=1.0, policy=hold)
    assert set(near) == {"humanoid3d_walk", "humanoid3d_run", "mean", "segments"}
    assert near["humanoid3d_walk"] < 0.003 and near["humanoid3d_run"] < 0.003
    # 1-second segments: the walk's 38 frames make two (from frames 0 and 30), the run's 24 one; every
    # segment of a cyclic clip runs its 30 steps, so the mean over segments weighs the walk twice.
    assert near["segments"] == 3
    assert near["mean"] == pytest.approx((2 * near["humanoid3d_walk"] + near["humanoid3d_run"]) / 3)
    # The untrained controller holds a T-pose and falls: tens of centimetres (measured 0.34 and 0.41 m).
    c = controller(character)
    far = tracking_error(c, character, walk_run, clip_seconds=2.0)
    assert far["humanoid3d_walk"] > 0.15 and far["humanoid3d_run"] > 0.15
    assert far == tracking_error(c, character, walk_run, clip_seconds=2.0)
    with pytest.raises(ValueError, match="controller or a policy"):
        tracking_error(None, character, walk_run)


def test_tracking_segments_divide_every_clip_into_consecutive_pieces(character, walk_run):
    """Fig. 14's 2-second clips, here of 10 steps: a cyclic clip's segments run their full length (through
    the next cycle), a one-shot clip's last one ends on its last frame."""
    walk = walk_run.clips[walk_run.clip_id("humanoid3d_walk")]
    one_shot = dataclasses.replace(walk, name="walk_once", loop=False)
    lib = MotionLibrary(character, [walk, one_shot])
    clips, starts, steps = tracking_segments(lib, seconds=1 / 3, control_hz=30)
    assert lib.num_frames.tolist() == [38, 38]
    assert clips.tolist() == [0, 0, 0, 0, 1, 1, 1, 1]
    assert starts.tolist() == [0, 10, 20, 30, 0, 10, 20, 30]
    assert steps.tolist() == [10, 10, 10, 10, 10, 10, 10, 7]  # frames 30 -> 37, the last one
    pd = reference_targets(lib)

    def hold(sim):  # on the reference's next pose before each step (see the test above)
        ref = lib.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        sim.set_state(np.arange(sim.num_envs), ref.qpos, np.zeros_like(ref.qvel))
        return pd(sim)

    out = tracking_error(None, character, lib, clip_seconds=1 / 3, policy=hold)
    assert out["segments"] == 8
    assert out["humanoid3d_walk"] < 0.003 and out["walk_once"] < 0.003
    # Frames 0-37 are tracked alike by both; the cyclic clip's last segment goes on to frames 38-39 (the next
    # cycle's 0-1), so the two means differ only by those two steps.
    assert out["humanoid3d_walk"] == pytest.approx(out["walk_once"], abs=5e-4)
    assert out["mean"] == pytest.approx((40 * out["humanoid3d_walk"] + 37 * out["walk_once"]) / 77)


def test_random_sampling_starts_anywhere_and_reports_falls_and_distance(character, walk_run):
    c = controller(character)
    out = random_sampling(c, character, walk_run, num_rollouts=6, seconds=40 / 30, seed=3)
    roots = out["roots"]
    assert roots.shape == (6, 41, 2) and np.allclose(roots[:, 0], 0.0)
    assert out["fell"] == 1.0  # the untrained T-pose topples within 40 steps
    end = np.linalg.norm(roots[:, -1], axis=-1).mean()
    path = np.linalg.norm(np.diff(roots, axis=1), axis=-1).sum(1).mean()
    assert out["distance"] == pytest.approx(end) and out["path"] == pytest.approx(path)
    assert out["distance"] <= out["path"] + 1e-12
    again = random_sampling(c, character, walk_run, num_rollouts=6, seconds=40 / 30, seed=3)
    np.testing.assert_array_equal(again["roots"], roots)
    assert c.training
