"""The task policy in the rollout worker: what it records, its frozen decoder, and its evaluation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from workers.evaluation.tasks import evaluate_task_policy
from workers.learners.task import TaskConfig, task_policy
from workers.learners.vae import VAEConfig, build_controller
from workers.losses.task import task_terms
from workers.rollout import RolloutWorker
from workers.task.policy import TaskRolloutPolicy

SKILL = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(32,))


def task_worker(character, library, task: str, sigma: float, num_envs: int = 4, seed: int = 0, **kw):
    config = TaskConfig(task=task, sigma=sigma, hidden=(32,), helper_hidden=(32,), change_rate=3.0, **kw)
    policy = TaskRolloutPolicy(character.num_bodies, character.num_actions, config, control_hz=30.0)
    worker = RolloutWorker(character, library, num_envs, policy, seed=seed)
    torch.manual_seed(0)
    controller = build_controller(character.num_bodies, character.num_actions, SKILL)
    policy.configure({"skill": {"config": SKILL, "module": controller.state_dict(), "prior_action": True}})
    module = task_policy(controller, character.num_actions, config)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(0.3 * torch.randn_like(p))  # a policy whose μ_g and helper are far from zero
    from workers.learners.base import Weights

    worker.set_weights(Weights(3, module.state_dict()))
    return worker, controller


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_the_worker_records_goals_rewards_and_the_helpers_deviation(character, walk_run, sigma):
    worker, _ = task_worker(character, walk_run, "heading", sigma)
    traj = worker.collect(40)
    goals, reward = traj.extras["goal"], traj.extras["reward"]
    assert goals.shape == (40, 4, 2) and traj.version == 3
    # The reward of each step is e^(-L_g) of the state it reached, for the goal it acted for.
    terms = task_terms("heading", torch.from_numpy(traj.next_states), torch.from_numpy(goals))
    expected = np.exp(-(2.0 * terms["heading"] + 1.0 * terms["speed"]).numpy())
    np.testing.assert_allclose(reward, expected, rtol=1e-5)
    # Goals change within episodes at the configured rate (3 per second here): some, not all, steps.
    changes = (np.abs(np.diff(goals, axis=0)).sum(-1) > 0) & ~traj.done[:-1]
    assert 0 < changes.mean() < 0.5
    deviation = traj.extras["helper_deviation"]
    if sigma == 0:
        assert not deviation.any()  # the applied action is the decoder's
    else:
        assert 0 < deviation.max() <= sigma


def test_the_progress_reward_is_how_much_nearer_the_step_brought_the_root(character, walk_run):
    """reward=progress (PhysicsVAE Sec. 5.2's point goal): d_{t-1} − d_t, the root's horizontal distance to the
    goal in force before the step minus after it, for that same goal (goals change within episodes here)."""
    worker, _ = task_worker(character, walk_run, "point_goal", 0.0, trainer="ppo", reward="progress")
    traj = worker.collect(40)
    goals = torch.from_numpy(traj.extras["goal"])
    before = task_terms("point_goal", torch.from_numpy(traj.states), goals)["distance"].numpy()
    after = task_terms("point_goal", torch.from_numpy(traj.next_states), goals)["distance"].numpy()
    np.testing.assert_allclose(traj.extras["reward"], before - after, atol=1e-5)
    assert (traj.extras["reward"] < 0).any() or (traj.extras["reward"] > 0).any()
    with pytest.raises(ValueError, match="task.reward: progress is the point goal's reward under the ppo trainer"):
        TaskConfig(task="heading", trainer="ppo", reward="progress")
    with pytest.raises(ValueError, match="task.reward: unknown"):
        TaskConfig(reward="sparse")


def test_the_ppo_task_policy_records_the_progress_reward_too(character, walk_run):
    """The PPO trainer's policy (ablation_sigma's) acts through its own path: the same d_{t-1} − d_t."""
    from workers.learners.base import Weights
    from workers.learners.ppo import PPOConfig
    from workers.task.policy import TaskPPOPolicy

    config = TaskConfig(task="point_goal", trainer="ppo", reward="progress", sigma=0.5, change_rate=3.0)
    ppo = PPOConfig(policy_hidden=(16,), value_hidden=(16,))
    policy = TaskPPOPolicy(character.num_bodies, character.num_actions, config, 30.0, ppo)
    worker = RolloutWorker(character, walk_run, 4, policy, seed=0)
    torch.manual_seed(0)
    controller = build_controller(character.num_bodies, character.num_actions, SKILL)
    policy.configure({"skill": {"config": SKILL, "module": controller.state_dict(), "prior_action": True}})
    worker.set_weights(Weights(1, policy.module.state_dict()))
    traj = worker.collect(30)
    goals = torch.from_numpy(traj.extras["goal"])
    before = task_terms("point_goal", torch.from_numpy(traj.states), goals)["distance"].numpy()
    after = task_terms("point_goal", torch.from_numpy(traj.next_states), goals)["distance"].numpy()
    np.testing.assert_allclose(traj.extras["reward"], before - after, atol=1e-5)


def test_evaluation_is_deterministic_and_measures_the_helper_in_degrees(character, walk_run):
    worker, _ = task_worker(character, walk_run, "point_goal", 0.5)
    a = evaluate_task_policy(worker.policy, character, walk_run, 3, 1.0, seed=7)
    b = evaluate_task_policy(worker.policy, character, walk_run, 3, 1.0, seed=7)
    assert a["return"] == b["return"] and a["style_deviation_deg"] == b["style_deviation_deg"]
    assert 0 < a["style_deviation_deg"] <= math.degrees(0.5)
    assert 0 <= a["return"] <= 1 and 0 < a["time_until_fall_mean"] <= 1.0
    assert worker.policy.stochastic  # evaluation acts with the mean, then gives the sampling back
    worker0, _ = task_worker(character, walk_run, "point_goal", 0.0)
    assert evaluate_task_policy(worker0.policy, character, walk_run, 3, 1.0, seed=7)["style_deviation_deg"] == 0.0


def test_the_worker_state_restores_its_goals(character, walk_run):
    worker, _ = task_worker(character, walk_run, "point_goal", 0.1, seed=1)
    worker.collect(5)
    state = worker.state_dict()
    first = worker.collect(10)
    worker.load_state_dict(state)
    again = worker.collect(10)
    np.testing.assert_array_equal(first.extras["goal"], again.extras["goal"])
    np.testing.assert_array_equal(first.states, again.states)
