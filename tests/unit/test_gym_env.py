"""The gymnasium adapter of the humanoid: API conformance, batching, seeding, reward, episode ends."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from workers.motion.library import MotionLibrary
from workers.rewards import imitation_reward
from workers.sim.gym_env import ENV_ID, HumanoidImitationEnv, HumanoidImitationVectorEnv, register


@pytest.fixture(scope="module")
def walk(character, clip_cache) -> MotionLibrary:
    return MotionLibrary.load(character, ["humanoid3d_walk"], fps=30, cache_dir=clip_cache)


@pytest.fixture
def env(character, walk) -> HumanoidImitationEnv:
    return HumanoidImitationEnv(character=character, library=walk)


def vec(character, walk, n=4, **kwargs) -> HumanoidImitationVectorEnv:
    return HumanoidImitationVectorEnv(num_envs=n, character=character, library=walk, **kwargs)


def reference_actions(e) -> np.ndarray:
    """PD targets holding each environment's next reference pose."""
    sim = e.sim
    return e.character.qpos_to_action(sim.library.state(sim.clip_id, sim.start_frame + sim.steps + 1).qpos)


@pytest.mark.filterwarnings("ignore:.*(infinity|normalized space).*:UserWarning")
def test_check_env_passes(env):
    check_env(env.unwrapped, skip_render_check=True)


def test_spaces(env, character):
    d = 16 * character.num_bodies + 3
    assert env.observation_space.shape == (2 * d,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (character.num_actions,) and env.action_space.dtype == np.float32
    assert np.allclose(env.action_space.low, -np.pi) and np.allclose(env.action_space.high, np.pi)
    obs, info = env.reset(seed=0)
    assert obs.shape == (2 * d,) and obs.dtype == np.float32 and isinstance(info, dict)


def test_vector_step_shapes_and_dtypes(character, walk):
    v = vec(character, walk, n=4)
    assert v.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, _ = v.reset(seed=0)
    d = v.single_observation_space.shape[0]
    assert obs.shape == (4, d) and obs.dtype == np.float32
    assert v.action_space.shape == (4, character.num_actions)
    obs, rew, term, trunc, info = v.step(v.action_space.sample())
    assert obs.shape == (4, d) and obs.dtype == np.float32 and obs in v.observation_space
    assert rew.shape == (4,) and rew.dtype == np.float64
    assert term.shape == trunc.shape == (4,) and term.dtype == trunc.dtype == np.bool_
    for k in ("fell", "tracking_failed", "clip_ended", "timeout"):
        assert info[k].shape == (4,) and info["_" + k].all()


def test_same_seed_same_observation(env, character, walk):
    a, _ = env.reset(seed=7)
    env.reset(seed=8)
    b, _ = env.reset(seed=7)
    assert np.array_equal(a, b)
    v = vec(character, walk, n=4)
    a, _ = v.reset(seed=7)
    b, _ = v.reset(seed=9)
    c, _ = v.reset(seed=7)
    assert np.array_equal(a, c) and not np.array_equal(a, b)


def test_reset_seeds_the_simulator_like_default_rng(env):
    env.reset(seed=5)
    expected = env.library.sample_starts(1, np.random.default_rng(5))
    assert (env.sim.clip_id[0], env.sim.start_frame[0]) == (expected[0][0], expected[1][0])


def test_reward_is_one_on_the_reference(character, walk):
    v = vec(character, walk, n=4)
    v.reset(seed=1)
    r, terms = imitation_reward(character, v.sim.kin_state(), v.sim.reference_state(), v._core.weights)
    assert np.allclose(r, 1.0, atol=1e-5)
    assert all(np.allclose(t, 1.0, atol=1e-5) for t in terms.values())


def test_actions_are_clipped_to_the_box(env):
    n = env.action_space.shape[0]
    env.reset(seed=2)
    a = env.step(np.full(n, 10.0, np.float32))[0]
    env.reset(seed=2)
    b = env.step(np.full(n, np.pi, np.float32))[0]
    assert np.array_equal(a, b)


def test_a_fall_terminates(character, walk):
    v = vec(character, walk, n=4)
    v.reset(seed=0)
    v.action_space.seed(0)
    for _ in range(90):
        _, _, term, trunc, info = v.step(v.action_space.sample())
        if (term & info["fell"]).any():
            assert not trunc[term & info["fell"]].any()
            return
    pytest.fail("random full-range PD targets never made the character fall")


def test_timeout_truncates(character, walk):
    e = HumanoidImitationEnv(max_episode_steps=3, character=character, library=walk)
    e.reset(seed=0)
    for t in range(3):
        _, r, term, trunc, info = e.step(reference_actions(e)[0])
        assert not term and trunc == (t == 2) and info["timeout"] == (t == 2)
        assert r > 0.0


def test_next_step_autoreset(character, walk):
    v = vec(character, walk, n=2, max_episode_steps=2)
    v.reset(seed=0)
    for _ in range(2):
        _, _, term, trunc, _ = v.step(reference_actions(v))
    assert (term | trunc).all()
    obs, rew, term, trunc, _ = v.step(reference_actions(v))
    assert (rew == 0).all() and not term.any() and not trunc.any()
    assert (v.sim.steps == 0).all()  # the step after the end was the reset
    expected = v._core.observe(v.library.features(v.sim.clip_id, v.sim.start_frame))
    assert np.array_equal(obs, expected)
    _, rew, _, _, _ = v.step(reference_actions(v))
    assert (rew > 0).all() and (v.sim.steps == 1).all()


def test_same_step_autoreset(character, walk):
    v = vec(character, walk, n=2, max_episode_steps=2, autoreset_mode="SameStep")
    assert v.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    v.reset(seed=0)
    v.step(reference_actions(v))
    obs, _, _, trunc, info = v.step(reference_actions(v))
    assert trunc.all() and info["_final_obs"].all() and info["final_info"]["timeout"].all()
    assert (v.sim.steps == 0).all()
    assert info["final_obs"][0].shape == obs[0].shape and not np.array_equal(info["final_obs"][0], obs[0])


def test_registered_ids(character, walk):
    register()  # idempotent
    e = gymnasium.make(ENV_ID, character=character, library=walk)
    assert isinstance(e.unwrapped, HumanoidImitationEnv)
    assert e.reset(seed=0)[0] in e.observation_space
    v = gymnasium.make_vec(
        ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", character=character, library=walk
    )
    assert isinstance(v, HumanoidImitationVectorEnv) and v.num_envs == 4
    assert v.reset(seed=0)[0].shape == (4,) + e.observation_space.shape
