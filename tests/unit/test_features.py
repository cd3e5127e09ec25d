"""State features s and Φ(s): sizes, layout, invariance to heading and horizontal position."""

import numpy as np
import pytest

from workers.body.features import StateLayout, amp_dim, amp_features, state_features
from workers.motion.library import transform_state
from workers.sim.env import BatchedSim


@pytest.fixture(scope="module")
def sim_states(character, walk_run):
    """Simulated (not reference) states: a few noisy control steps after reset."""
    sim = BatchedSim(character, walk_run, num_envs=8, seed=3)
    rng = np.random.default_rng(3)
    ref = sim.reference_state()
    for _ in range(5):
        r = sim.step(character.qpos_to_action(ref.qpos) + rng.normal(0, 0.2, (8, 28)))
        ref = sim.reference_state()
    return r.kin


def test_sizes_and_layout(character, sim_states):
    s = state_features(sim_states)
    layout = StateLayout(character.num_bodies)
    assert s.shape == (8, 243) and layout.dim == 243
    phi = amp_features(character, sim_states)
    assert phi.shape == (8, amp_dim(character)) and amp_dim(character) == 105
    # Heights are the bodies' z; the root's relative position is zero.
    np.testing.assert_allclose(s[:, layout.height], sim_states.xpos[..., 2], atol=1e-6)
    np.testing.assert_allclose(s[:, layout.pos][:, :3], 0.0, atol=1e-6)
    # The 6D rotation of an upright body has unit columns.
    rot6 = s[:, layout.rot].reshape(8, 15, 6)
    np.testing.assert_allclose(np.linalg.norm(rot6[..., :3], axis=-1), 1.0, atol=1e-5)


@pytest.mark.parametrize("yaw", [0.7, -2.5, np.pi])
def test_invariant_to_heading_and_horizontal_position(character, sim_states, yaw):
    n = len(sim_states)
    moved = transform_state(sim_states, np.full(n, yaw), np.tile([3.0, -1.5, 0.0], (n, 1)))
    assert not np.allclose(moved.xpos, sim_states.xpos)
    np.testing.assert_allclose(state_features(moved), state_features(sim_states), atol=1e-5)
    np.testing.assert_allclose(amp_features(character, moved), amp_features(character, sim_states), atol=1e-5)


def test_features_change_with_height(character, sim_states):
    lifted = transform_state(sim_states, np.zeros(len(sim_states)), np.tile([0.0, 0.0, 0.1], (len(sim_states), 1)))
    assert not np.allclose(state_features(lifted), state_features(sim_states))
    assert not np.allclose(amp_features(character, lifted), amp_features(character, sim_states))


def test_precomputed_reference_features_match(walk_run):
    clip_ids = np.array([0, 0, 1, 1])
    frames = np.array([0, 50, 3, 100])  # frames past the end of the cycle included
    np.testing.assert_allclose(
        walk_run.features(clip_ids, frames), state_features(walk_run.state(clip_ids, frames)), atol=1e-5
    )
