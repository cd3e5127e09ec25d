"""workers.models.device_features: what a worker beside a GPU simulator computes there, against the NumPy originals."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.body.features import amp_features
from workers.models import device_features
from workers.models.body_state import pack
from workers.models.device_features import DeviceState
from workers.sim.env import BatchedSim


@pytest.fixture(scope="module")
def kin(character, walk_run):
    """Simulated states, turned and moving: a few noisy control steps after resets at several frames."""
    sim = BatchedSim(character, walk_run, num_envs=8, seed=3)
    rng = np.random.default_rng(3)
    for _ in range(5):
        r = sim.step(character.qpos_to_action(sim.reference_state().qpos) + rng.normal(0, 0.2, (8, 28)))
    return r.kin


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
