"""The rollout worker: shapes, version tags, determinism, resets, resume; its trajectories in the replay buffer."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from workers.learners.base import Weights
from workers.learners.vae import VAEConfig, build_controller
from workers.models import body_state
from workers.policies import VAEPolicy
from workers.replay.buffer import ReplayBuffer
from workers.rollout import RolloutWorker

SMALL = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(64,))
M = 4


@pytest.fixture(scope="module")
def weights(character) -> Weights:
    torch.manual_seed(11)
    controller = build_controller(character.num_bodies, character.num_actions, SMALL)
    return Weights(7, {k: v.clone() for k, v in controller.state_dict().items()})


def make_worker(
    character, library, weights=None, seed=0, worker_id=0, action_noise=0.05, prior_probability=0.4
) -> RolloutWorker:
    config = dataclasses.replace(SMALL, action_noise=action_noise)
    policy = VAEPolicy(character.num_bodies, character.num_actions, config, prior_probability)
    worker = RolloutWorker(character, library, M, policy, seed=seed, worker_id=worker_id)
    if weights is not None:
        worker.set_weights(weights)
    return worker


@pytest.fixture(scope="module")
def collected(character, walk_run, weights):
    """60 steps (2 s) of 4 environments; the untrained policy falls within about a second."""
    worker = make_worker(character, walk_run, weights, seed=3, worker_id=2)
    return worker, worker.collect(60)


def test_shapes_and_tags(character, walk_run, collected):
    worker, traj = collected
    b, a = character.num_bodies, character.num_actions
    assert traj.states.shape == traj.next_states.shape == (60, M, b, 13)
    assert traj.actions.shape == (60, M, a)
    assert traj.done.shape == traj.clip_id.shape == traj.frame.shape == (60, M)
    assert traj.states.dtype == traj.next_states.dtype == traj.actions.dtype == np.float32
    assert traj.done.dtype == bool
    assert (traj.version, traj.worker) == (7, 2)
    assert np.isfinite(traj.states).all() and np.isfinite(traj.actions).all()
    assert traj.done.any(), "the untrained policy should fall within 2 s"
    stats = worker.stats()
    assert stats["steps"] == 60 * M
    assert stats["episodes"] == traj.done.sum()
    assert stats["falls"] + stats["tracking_failures"] + stats["clip_ends"] + stats["timeouts"] >= stats["episodes"]
    assert 0 < stats["mean_episode_length"] <= 60
    assert make_worker(character, walk_run).collect(1).version == -1  # no weights received yet


def test_transitions_chain_and_resets_start_on_the_reference(walk_run, collected):
    _, traj = collected
    cont = ~traj.done[:-1]  # [T-1, M]
    # Without a reset the next state is the following state, and the reference advances one frame.
    np.testing.assert_array_equal(traj.next_states[:-1][cont], traj.states[1:][cont])
    np.testing.assert_array_equal(traj.frame[1:][cont], traj.frame[:-1][cont] + 1)
    np.testing.assert_array_equal(traj.clip_id[1:][cont], traj.clip_id[:-1][cont])
    # After a reset the state is the reference state at the new start, and differs from the true successor.
    t, e = np.nonzero(traj.done[:-1])
    assert len(t) > 0
    ref = body_state.pack(walk_run.state(traj.clip_id[t + 1, e], traj.frame[t + 1, e]))
    np.testing.assert_allclose(traj.states[t + 1, e], ref, atol=1e-5)
    assert not np.allclose(traj.next_states[t, e], traj.states[t + 1, e])


def test_same_seed_same_trajectories(character, walk_run, weights):
    a = make_worker(character, walk_run, weights, seed=5).collect(20)
    b = make_worker(character, walk_run, weights, seed=5).collect(20)
    c = make_worker(character, walk_run, weights, seed=6).collect(20)
    for field in ("states", "next_states", "actions", "done", "clip_id", "frame"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(a.actions, c.actions)


def test_noise_and_prior_choice(character, walk_run, weights):
    """With no noise and the prior never used, actions are the policy's at the posterior sample;
    raising the noise changes them by about its size."""
    quiet = make_worker(character, walk_run, weights, seed=1, action_noise=0.0, prior_probability=0.0)
    noisy = make_worker(character, walk_run, weights, seed=1, action_noise=0.5, prior_probability=0.0)
    assert not quiet.policy.use_prior.any()
    diff = noisy.collect(1).actions - quiet.collect(1).actions
    assert diff.std() == pytest.approx(0.5, rel=0.2)
    assert make_worker(character, walk_run, weights, prior_probability=1.0).policy.use_prior.all()
    with pytest.raises(ValueError, match="prior_probability"):
        make_worker(character, walk_run, prior_probability=1.5)


def test_state_dict_resumes_exactly(character, walk_run, weights):
    worker = make_worker(character, walk_run, weights, seed=4)
    worker.collect(13)
    state = copy.deepcopy(worker.state_dict())
    expected = worker.collect(30)
    resumed = make_worker(character, walk_run, weights, seed=99)
    resumed.load_state_dict(state)
    got = resumed.collect(30)
    for field in ("states", "next_states", "actions", "done", "clip_id", "frame"):
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    assert got.version == expected.version == 7
    assert resumed.stats()["episodes"] == worker.stats()["episodes"]


def test_windows_from_real_trajectories_run_across_collects(character, walk_run, weights):
    worker = make_worker(character, walk_run, weights, seed=8, worker_id=1)
    buffer = ReplayBuffer(2_000, character.num_bodies, character.num_actions, seed=0)
    successor = {}
    for _ in range(3):
        traj = worker.collect(8)
        buffer.add(traj)
        flat = (-1,) + traj.states.shape[2:]
        for s, n in zip(traj.states.reshape(flat), traj.next_states.reshape(flat), strict=True):
            successor[s.tobytes()] = n
    batch = buffer.sample_windows(64, 12)  # longer than one collect of 8 steps
    for window in batch.states:
        for j in range(12):
            np.testing.assert_array_equal(successor[window[j].tobytes()], window[j + 1])


def test_one_worker_serves_the_vae_controller_and_the_actor_critic(character, walk_run, weights):
    """The same RolloutWorker runs either policy; PPO's extras and AMP's Φ come with the actor-critic's."""
    from workers.body.features import amp_dim
    from workers.models.actor_critic import ActorCritic
    from workers.policies import GaussianPolicy
    from workers.recorders import AMPFeatures, ImitationReward

    vae = make_worker(character, walk_run, weights).collect(10)
    assert set(vae.extras) == {"truncated"}  # the VAE's learners need only the body states and actions

    s_dim = 16 * character.num_bodies + 3
    module = ActorCritic(2 * s_dim, character.num_actions, action_std=0.05, policy_hidden=(32,), value_hidden=(32,))
    recorders = [AMPFeatures(character), ImitationReward(character)]
    policy = GaussianPolicy(module, obs="imitation", residual=True)
    worker = RolloutWorker(character, walk_run, M, policy, seed=2, recorders=recorders)
    worker.set_weights(Weights(3, module.state_dict()))
    traj = worker.collect(40)
    x = traj.extras
    assert x["obs"].shape == (40, M, 2 * s_dim) and x["log_prob"].shape == (40, M)
    assert x["amp_obs"].shape == x["amp_next_obs"].shape == (40, M, amp_dim(character))
    assert x["last_obs"].shape == (M, 2 * s_dim) and traj.version == 3
    # The PD targets applied are the reference's next pose plus the sampled offset.
    t, m = 0, 0
    ref = walk_run.state(traj.clip_id[t : t + 1, m], traj.frame[t : t + 1, m] + 1)
    np.testing.assert_allclose(traj.actions[t, m], character.qpos_to_action(ref.qpos)[0] + x["action"][t, m], atol=1e-5)
    # Φ(s') of a step is Φ(s) of the next one unless the environment was reset in between.
    cont = ~traj.done[:-1]
    np.testing.assert_allclose(x["amp_next_obs"][:-1][cont], x["amp_obs"][1:][cont], atol=1e-6)
    assert ((x["reward"] >= 0) & (x["reward"] <= 1)).all() and x["reward"].max() > 0.01
    np.testing.assert_allclose(np.prod([x[f"reward/{k}"] for k in ("pose", "velocity", "end_effector", "root")], 0),
                               x["reward"], rtol=1e-4, atol=1e-30)  # fmt: skip
    # log π(a | o) recorded while acting is the policy's log-probability of the recorded sample.
    lp = module.log_prob(torch.from_numpy(x["obs"][5]), torch.from_numpy(x["action"][5]))
    np.testing.assert_allclose(lp.detach().numpy(), x["log_prob"][5], rtol=1e-4, atol=1e-4)
