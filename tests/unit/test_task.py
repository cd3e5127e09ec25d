"""Task losses, goal observations and the task policy's helper branch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from workers.learners.task import TaskBatch, TaskConfig, TaskLearner
from workers.losses.task import angle_difference, fall_penalty, task_loss
from workers.models import body_state as B
from workers.models.task import TaskPolicy, goal_observation
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


def test_point_goal_and_steering_terms():
    w = {"distance": 1.0, "heading": 2.0, "direction": 2.0, "speed": 1.0, "fall": 1.0}
    _, terms = task_loss("point_goal", standing(), torch.tensor([[4.0, 6.0]]), w, 0.5)
    torch.testing.assert_close(terms["distance"], torch.tensor([5.0]))  # (3, 4) away
    total, _ = task_loss("steering", standing(0.0, (0, 2.0, 0)), torch.tensor([[0.0, math.pi / 2, 2.0]]), w, 0.5)
    torch.testing.assert_close(total, torch.zeros(1), atol=1e-4, rtol=0)


@pytest.mark.parametrize("task", ["heading", "steering", "point_goal", "height"])
def test_goal_observation_is_invariant_to_turning_the_world(task):
    # Rotate the character and the goal together about z: the policy must see the same thing.
    bs = standing(0.3, (0.5, 0.2, 0.0))
    goals = {"heading": [0.8, 1.0], "steering": [0.8, -0.4, 1.0], "point_goal": [3.0, -1.0], "height": [1.0]}
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
    if task == "point_goal":
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
    s, g, eps = torch.randn(5, 243), torch.randn(5, 3), torch.randn(5, 8)
    action, mu_g = policy(vae, s, g)
    assert torch.equal(action, vae.act(s, vae.prior_dist(s).mean + mu_g))  # bit for bit
    applied, decoded, _ = policy.act(vae, s, g, eps)
    assert torch.equal(applied, decoded)
    # Eq. 21's sample: the prior's mean plus μ_g, plus the prior's std (σ_p = 0.3 here) times the noise.
    z, mu_g = policy.latent(vae, s, g, eps)
    torch.testing.assert_close(z, vae.prior_dist(s).mean + mu_g + 0.3 * eps)


@pytest.mark.parametrize("sigma", [0.1, 0.5])
def test_with_helper_no_joint_moves_more_than_sigma_from_the_decoder(sigma):
    torch.manual_seed(0)
    vae = VAEController(243, 28, latent_dim=8, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,))
    policy = TaskPolicy(243, 3, 8, 28, hidden=(16,), helper_hidden=(16,), sigma=sigma)
    with torch.no_grad():
        for p in policy.helper.parameters():
            p.mul_(100.0)
    applied, decoded, _ = policy.act(vae, 10 * torch.randn(256, 243), torch.randn(256, 3), torch.randn(256, 8))
    deviation = (applied - decoded).abs()
    assert deviation.max() <= sigma * (1 + 1e-6) and deviation.max() > 0.9 * sigma


def test_without_prior_action_z_is_the_task_output():
    """PULSE's ablation row: z = μ_task, no residual on the prior's mean."""
    torch.manual_seed(0)
    vae = VAEController(243, 28, prior="learned", latent_dim=8, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,))
    policy = TaskPolicy(243, 3, 8, 28, hidden=(16,), prior_action=False)
    s, g = torch.randn(4, 243), torch.randn(4, 3)
    z, mu_g = policy.latent(vae, s, g)
    assert torch.equal(z, mu_g)


def test_task_learning_leaves_the_skill_model_alone_and_decays_its_step(walk_run):
    torch.manual_seed(0)
    vae = VAEController(243, 28, latent_dim=8, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,))
    wm = WorldModel(15, 28, hidden=(16,))
    frozen = {
        k: v.clone() for k, v in {**vae.state_dict(), **{f"wm.{k}": v for k, v in wm.state_dict().items()}}.items()
    }
    config = TaskConfig(hidden=(16,), sigma=0.1, rollout_steps=3, lr=1e-3, lr_decay=0.5, lr_floor=0.2)
    learner = TaskLearner(vae, wm, 28, config)
    states = torch.as_tensor(B.pack(walk_run.state(np.zeros(4, int), np.arange(4))))
    policy_before = [p.detach().clone() for p in learner.policy.parameters()]
    lrs = []
    for _ in range(4):
        learner.update(TaskBatch(states, torch.rand(4, 3, 2)))
        lrs.append(learner.optimizer.param_groups[0]["lr"])
    after = {**vae.state_dict(), **{f"wm.{k}": v for k, v in wm.state_dict().items()}}
    assert all(torch.equal(frozen[k], after[k]) for k in frozen)  # decoder, prior, world model untouched
    assert any(not torch.equal(a, b) for a, b in zip(policy_before, learner.policy.parameters(), strict=True))
    np.testing.assert_allclose(lrs, [1e-3, 5e-4, 2.5e-4, 2e-4])  # lr · max(0.5^update, 0.2)


def test_goal_buffer_keeps_goal_sequences_aligned_with_their_start_states():
    from workers.learners.task import GoalBuffer

    buf = GoalBuffer(capacity=12)
    for c in range(3):  # collections of T = 3 steps x M = 2 environments; state and goal encode (c, t, m)
        states = np.zeros((3, 2, 15, 13), np.float32)
        goals = np.zeros((3, 2, 2), np.float32)
        for t in range(3):
            for m in range(2):
                states[t, m, 0, 0] = goals[t, m, 0] = 100 * c + 10 * t + m
        buf.add(states, goals)
    assert len(buf) == 12 and buf.chunks[0][0][0, 0, 0, 0] == 100  # the oldest collection went
    batch = buf.sample(64, 4, np.random.default_rng(0))
    start = batch.states[:, 0, 0].numpy()
    seq = batch.goals[..., 0].numpy()
    t = (start % 100) // 10
    for k in range(4):  # the goals that followed each start, the last one repeated past the collection's end
        np.testing.assert_array_equal(seq[:, k], start + 10 * np.minimum(k, 2 - t))


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


def test_the_model_based_trainer_refuses_a_layer_it_cannot_roll_out():
    """PhysicsVAE's Table 2 layer (world_model.kind=regress) predicts features, not body states."""
    from workers.models.world_model import StateRegressor

    vae = VAEController(243, 28, latent_dim=8, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,))
    with pytest.raises(ValueError, match="integrating world model"):
        TaskLearner(vae, StateRegressor(15, 28, hidden=(8,)), 28, TaskConfig(hidden=(16,)))
