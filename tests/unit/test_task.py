"""Task losses, goal observations and the task policy's helper branch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from workers.learners.task import TaskBatch, TaskConfig, TaskLearner
from workers.losses.task import angle_difference, fall_penalty, goal_observation, task_loss
from workers.models import body_state as B
from workers.models.task import TaskPolicy
from workers.models.vae import VAEController
from workers.models.world_model import WorldModel


def standing(yaw: float = 0.0, vel=(0.0, 0.0, 0.0), height: float = 0.9) -> torch.Tensor:
    """One character of 15 bodies, root at (1, 2, height) facing `yaw`, root moving at `vel`."""
    bs = torch.zeros(1, 15, 13)
    bs[..., 3] = math.cos(yaw / 2)
    bs[..., 6] = math.sin(yaw / 2)
    bs[:, 0, :3] = torch.tensor([1.0, 2.0, height])
    bs[:, 0, 7:10] = torch.tensor(vel)
    return bs


def test_heading_loss_known_answers():
    w = {"heading": 2.0, "speed": 1.0, "fall": 1.0}
    # Facing and moving along θ* = π/2 at exactly v* = 1.5: no loss.
    total, terms = task_loss("heading", standing(math.pi / 2, (0, 1.5, 0)), torch.tensor([[math.pi / 2, 1.5]]), w, 0.5)
    torch.testing.assert_close(total, torch.zeros(1), atol=1e-6, rtol=0)
    # Facing 0 instead, still moving along y at 1.5: heading error π/2, weighted 2 → π.
    total, terms = task_loss("heading", standing(0.0, (0, 1.5, 0)), torch.tensor([[math.pi / 2, 1.5]]), w, 0.5)
    torch.testing.assert_close(total, torch.tensor([math.pi]))
    # Standing still with v* = 0.5: speed error 0.5 / max(0.5, 1) = 0.5.
    _, terms = task_loss("heading", standing(), torch.tensor([[0.0, 0.5]]), w, 0.5)
    torch.testing.assert_close(terms["speed"], torch.tensor([0.5]))


def test_angle_difference_wraps():
    torch.testing.assert_close(angle_difference(torch.tensor(3.0), torch.tensor(-3.0)), torch.tensor(2 * math.pi - 6))


def test_fall_penalty_and_height():
    torch.testing.assert_close(fall_penalty(standing(height=0.2), 0.5), torch.tensor([0.3]))
    assert float(fall_penalty(standing(height=0.9), 0.5)) == 0.0
    _, terms = task_loss("height", standing(height=0.8), torch.tensor([[1.0]]), {"height": 1.0, "fall": 1.0}, 0.5)
    torch.testing.assert_close(terms["height"], torch.tensor([-0.8]))  # higher is better for H = +1


def test_location_and_steering_terms():
    w = {"distance": 1.0, "heading": 2.0, "direction": 2.0, "speed": 1.0, "fall": 1.0}
    _, terms = task_loss("location", standing(), torch.tensor([[4.0, 6.0]]), w, 0.5)
    torch.testing.assert_close(terms["distance"], torch.tensor([5.0]))  # (3, 4) away
    total, _ = task_loss("steering", standing(0.0, (0, 2.0, 0)), torch.tensor([[0.0, math.pi / 2, 2.0]]), w, 0.5)
    torch.testing.assert_close(total, torch.zeros(1), atol=1e-4, rtol=0)


@pytest.mark.parametrize("task", ["heading", "steering", "location", "height"])
def test_goal_observation_is_invariant_to_turning_the_world(task):
    # Rotate the character and the goal together about z: the policy must see the same thing.
    bs = standing(0.3, (0.5, 0.2, 0.0))
    goals = {"heading": [0.8, 1.0], "steering": [0.8, -0.4, 1.0], "location": [3.0, -1.0], "height": [1.0]}
    goal = torch.tensor([goals[task]])
    turn = 1.1
    c, s = math.cos(turn), math.sin(turn)
    bs2 = standing(0.3 + turn, (c * 0.5 - s * 0.2, s * 0.5 + c * 0.2, 0.0))
    bs2[:, 0, :2] = torch.tensor([c * 1.0 - s * 2.0, s * 1.0 + c * 2.0])
    goal2 = goal.clone()
    if task in ("heading", "steering"):
        goal2[0, 0] += turn
    if task == "steering":
        goal2[0, 1] += turn
    if task == "location":
        goal2[0] = torch.tensor([c * 3.0 + s * 1.0, s * 3.0 - c * 1.0])
    torch.testing.assert_close(goal_observation(task, bs, goal), goal_observation(task, bs2, goal2), atol=1e-5, rtol=0)


@pytest.mark.parametrize("sigma", [0.1, 0.5, 1.0])
def test_helper_offset_never_exceeds_sigma(sigma):
    torch.manual_seed(0)
    policy = TaskPolicy(243, 3, 8, 28, hidden=(16,), helper_hidden=(16,), sigma=sigma)
    with torch.no_grad():
        for p in policy.helper.parameters():
            p.mul_(1000.0)  # saturate tanh: the offset must still stay within σ
    s, z = 10 * torch.randn(512, 243), 10 * torch.randn(512, 8)
    offset = policy.helper_offset(s, z)
    assert offset.abs().max() <= sigma
    assert offset.abs().max() > 0.99 * sigma  # and it can reach it


def test_without_helper_the_action_is_the_decoders():
    torch.manual_seed(0)
    vae = VAEController(243, 28, latent_dim=8, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,))
    policy = TaskPolicy(243, 3, 8, 28, hidden=(16,), sigma=0.0)
    s, g = torch.randn(5, 243), torch.randn(5, 3)
    action, mu_g = policy(vae, s, g)
    torch.testing.assert_close(action, vae.act(s, vae.prior_dist(s).mean + mu_g))


def test_task_learner_updates_and_rejects_unknown_task(walk_run):
    torch.manual_seed(0)
    vae = VAEController(243, 28, latent_dim=8, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,))
    wm = WorldModel(15, 28, hidden=(16,))
    learner = TaskLearner(vae, wm, 28, TaskConfig(hidden=(16,), sigma=0.1, rollout_steps=3, lr=1e-3))
    states = torch.as_tensor(B.pack(walk_run.state(np.zeros(4, int), np.arange(4))))
    m = learner.update(TaskBatch(states, torch.rand(4, 3, 2)))
    assert math.isfinite(m["loss"]) and {"heading", "speed", "fall", "latent"} <= m.keys()
    assert not any(p.requires_grad for p in vae.parameters())
    with pytest.raises(ValueError, match="task.task: unknown task 'dance'"):
        TaskConfig(task="dance")
    with pytest.raises(ValueError, match="task.sigma must be non-negative"):
        TaskConfig(sigma=-0.1)
