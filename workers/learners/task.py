"""Model-based task learning through the frozen world model and VAE controller (ControlVAE §4.2).

Each update rolls the task policy out for T steps in the world model from buffer
states, under a recorded goal sequence, and minimises Eq. 22:
Σ_t [L_g(s_t) + L_fall(s_t)] + w_z Σ_t ‖μ_g‖², averaged over steps and trajectories.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from workers.learners.base import Learner, Weights, as_tensor, make_optimizer
from workers.losses.task import DEFAULT_WEIGHTS, GOAL_DIMS, goal_observation, goal_observation_dim, task_loss
from workers.models import body_state
from workers.models.task import TaskPolicy
from workers.models.vae import VAEController
from workers.models.world_model import WorldModel


@dataclass
class TaskConfig:
    # heading | height | steering | location
    task: str = "heading"
    # μ_g network and helper branch H hidden layers (PhysicsVAE: task encoder (256, 128), helper (128, 128)).
    hidden: tuple[int, ...] = (256, 128)
    helper_hidden: tuple[int, ...] = (128, 128)
    activation: str = "elu"
    # σ of the helper branch Δa = σ·tanh(H(s, z)); 0 turns it off (PhysicsVAE: 0.1 baseline, 1.0 rough terrain).
    sigma: float = 0.0
    # w_z on ‖μ_g‖², keeping the task policy near the prior (ControlVAE: 20).
    w_z: float = 20.0
    # Weights of the task's named terms and of the fall penalty.
    weights: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_WEIGHTS))
    # Root height below which L_fall grows (ControlVAE: 0.5 m).
    fall_height: float = 0.5
    # Synthetic rollouts: length T (ControlVAE 16) and number per update (256).
    rollout_steps: int = 16
    batch_size: int = 256
    optimizer: str = "radam"
    lr: float = 1e-4
    grad_clip: float = 1.0

    def __post_init__(self) -> None:
        if self.task not in GOAL_DIMS:
            raise ValueError(f"task.task: unknown task {self.task!r}; expected one of {sorted(GOAL_DIMS)}")
        if self.sigma < 0:
            raise ValueError(f"task.sigma must be non-negative, got {self.sigma}")
        if self.w_z < 0:
            raise ValueError(f"task.w_z must be non-negative, got {self.w_z}")


@dataclass
class TaskBatch:
    """Start body states [N, B, 13] and the goal at every step [N, T, G] (world frame)."""

    states: torch.Tensor | np.ndarray
    goals: torch.Tensor | np.ndarray


class TaskLearner(Learner):
    name = "task"

    def __init__(
        self,
        controller: VAEController,
        world_model: WorldModel,
        action_dim: int,
        config: TaskConfig | None = None,
    ):
        self.config = c = config or TaskConfig()
        state_dim = controller.state_norm.mean.shape[0]
        self.policy = TaskPolicy(
            state_dim,
            goal_observation_dim(c.task),
            controller.latent_dim,
            action_dim,
            c.hidden,
            c.helper_hidden,
            c.sigma,
            c.activation,
        )
        super().__init__(self.policy, make_optimizer(c.optimizer, self.policy.parameters(), c.lr), c.grad_clip)
        self.controller = controller.requires_grad_(False).eval()
        self.world_model = world_model.requires_grad_(False).eval()

    def set_frozen_weights(self, controller: Weights | None = None, world_model: Weights | None = None) -> None:
        if controller is not None:
            self.controller.load_state_dict(controller.state)
        if world_model is not None:
            self.world_model.load_state_dict(world_model.state)

    def before_update(self, batch: TaskBatch) -> None:
        self.policy.state_norm.update(body_state.features(as_tensor(batch.states)))

    def loss(self, batch: TaskBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        c = self.config
        bs, goals = as_tensor(batch.states), as_tensor(batch.goals)
        totals, reg = [], []
        sums: dict[str, torch.Tensor] = {}
        for t in range(goals.shape[1]):
            goal = goals[:, t]
            action, mu_g = self.policy(self.controller, body_state.features(bs), goal_observation(c.task, bs, goal))
            bs = self.world_model(bs, action)
            total, terms = task_loss(c.task, bs, goal, c.weights, c.fall_height)
            totals.append(total)
            reg.append((mu_g**2).sum(-1))
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + v.mean()
        steps = goals.shape[1]
        task = torch.stack(totals, 1).mean()
        latent = torch.stack(reg, 1).mean()
        out = {k: v / steps for k, v in sums.items()}
        out["task"], out["latent"] = task, latent
        return task + c.w_z * latent, out

    @torch.no_grad()
    def evaluate(self, batch: TaskBatch) -> dict[str, float]:
        """The loss terms of a batch without a step."""
        self.policy.eval()
        total, terms = self.loss(batch)
        return {"loss": float(total), **{k: float(v) for k, v in terms.items()}}
