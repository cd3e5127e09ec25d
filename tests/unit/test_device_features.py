"""workers.models.device_features: what a worker beside a GPU simulator computes there, against the NumPy originals."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.body.features import amp_features
from workers.models import device_features
from workers.models.body_state import features, pack
from workers.models.device_features import DeviceState
from workers.sim.env import BatchedSim


@pytest.fixture(scope="module")
def stepped(character, walk_run):
    """A simulator after a few noisy control steps from resets at several frames: turned, moving characters."""
    sim = BatchedSim(character, walk_run, num_envs=8, seed=3)
    rng = np.random.default_rng(3)
    for _ in range(5):
        sim.step(character.qpos_to_action(sim.reference_state().qpos) + rng.normal(0, 0.1, (8, 28)))
    return sim


@pytest.fixture(scope="module")
def kin(stepped):
    return stepped.kin_state()


def device_state(kin) -> DeviceState:
    return DeviceState(*(torch.as_tensor(a, dtype=torch.float32) for a in (kin.qpos, kin.qvel, pack(kin))))


def test_amp_features_are_the_numpy_ones(character, kin):
    want = amp_features(character, kin)
    got = device_features.amp_features(character, device_state(kin))
    assert got.dtype == torch.float32 and got.shape == want.shape
    assert np.ptp(want[:, 0]) > 0 and np.abs(want).max() > 1  # heights and velocities that differ
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=2e-5)


def test_rows_pick_environments(kin):
    state = device_state(kin)
    part = state.rows(np.array([5, 1]))
    np.testing.assert_array_equal(part.body_states.numpy(), state.body_states.numpy()[[5, 1]])
    np.testing.assert_array_equal(part.qvel.numpy(), kin.qvel[[5, 1]].astype(np.float32))


def test_the_reference_on_the_device_is_the_librarys_through_cycles(walk_run):
    """Frames past a looping clip's end are turned and moved by whole cycles, as `MotionLibrary.state` does."""
    ref = device_features.DeviceReference(walk_run, "cpu")
    walk = walk_run.clip_id("humanoid3d_walk")
    n = int(walk_run.num_frames[walk])
    clips = np.array([walk, walk, walk, 1 - walk])
    frames = np.array([3, n + 5, 4 * n + 2, 7])  # no cycle, one, four; the other clip
    want = walk_run.state(clips, frames)
    assert np.abs(want.xpos[2, 0, :2] - walk_run.state(clips[:1], frames[2:3] % n).xpos[0, 0, :2]).max() > 1.0
    got = ref.state(clips, frames)
    np.testing.assert_allclose(got.qpos.numpy(), want.qpos, rtol=0, atol=2e-5)
    np.testing.assert_allclose(got.qvel.numpy(), want.qvel, rtol=0, atol=2e-5)
    np.testing.assert_allclose(got.body_states.numpy(), pack(want), rtol=0, atol=2e-5)
    np.testing.assert_array_equal(ref.frame_features(clips, frames).numpy(), walk_run.features(clips, frames))
    targets = ref.pd_targets(clips, frames)  # joints only: the stored frame's whatever the cycle
    np.testing.assert_array_equal(targets.numpy(), walk_run.pd_targets(clips, frames))
    assert np.abs(targets[1].numpy() - walk_run.pd_targets(clips[:1], frames[:1])[0]).max() > 1e-2


def test_rewards_are_the_numpy_ones(character, walk_run, stepped, kin):
    from workers.body.features import state_features
    from workers.rewards import imitation_errors, imitation_reward, tracking_reward

    clips, frames = stepped.clip_id, stepped.start_frame + stepped.steps  # each character's own reference
    ref = walk_run.state(clips, frames)
    on_ref = device_features.DeviceReference(walk_run, "cpu").state(clips, frames)
    want_errors = imitation_errors(character, kin, ref)
    errors = device_features.imitation_errors(character, device_state(kin), on_ref)
    for k, v in want_errors.items():
        assert v.min() > 1e-4, k  # every term away from its reference
        np.testing.assert_allclose(errors[k].numpy(), v, rtol=1e-3, atol=1e-5, err_msg=k)
    weights = {"pose": 0.2, "velocity": 0.01, "end_effector": 4.0, "root": 1.0}  # rewards neither 0 nor 1
    want, want_terms = imitation_reward(character, kin, ref, weights)
    got, terms = device_features.imitation_reward(character, device_state(kin), on_ref, weights)
    assert 0.1 < np.median(want) and want.max() < 0.99 and np.ptp(want) > 0.01, want
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-4)
    for k, v in want_terms.items():
        np.testing.assert_allclose(terms[k].numpy(), v, rtol=0, atol=1e-4, err_msg=k)
    weights = np.linspace(0.5, 2.0, state_features(kin).shape[1])
    s, s_ref = state_features(kin), walk_run.features(clips, frames)
    got = device_features.tracking_reward(
        features(device_state(kin).body_states), torch.as_tensor(s_ref), torch.as_tensor(weights), 20.0
    )
    np.testing.assert_allclose(got.numpy(), tracking_reward(s, s_ref, weights), rtol=0, atol=1e-5)
