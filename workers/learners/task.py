"""Model-based task learning through the frozen world model and VAE controller (ControlVAE §4.2).

Each update rolls the task policy out for T steps in the world model from buffer
states, under the goal sequence recorded after each (`GoalBuffer`, ControlVAE's B_g
of 4096 simulated states), and minimises Eq. 22:
Σ_t [L_g(s_t) + L_fall(s_t)] + w_z Σ_t ‖μ_g‖², averaged over steps and trajectories.
z is sampled around μ_p + μ_g with the prior's std by reparameterisation (Eq. 21),
and the step size decays as lr · max(decay^update, floor) (ControlVAE §5.5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from workers.learners.base import Learner, Weights, make_optimizer
from workers.losses.task import DEFAULT_WEIGHTS, GOAL_DIMS, task_loss
from workers.models import body_state
from workers.models.task import TaskPolicy, goal_observation, goal_observation_dim
from workers.models.vae import VAEController
from workers.models.world_model import WorldModel

TRAINERS = ("model", "ppo")
TASK_REWARDS = ("exp", "progress")


@dataclass
class TaskConfig:
    # heading | steering | point_goal | height | vr (workers.losses.task)
    task: str = "heading"
    # model: through the frozen world model (ControlVAE §4.2); ppo: PPO in the simulator, reward e^(-L_g).
    trainer: str = "model"
    # The prior type of the skill stage, a label for sweeps whose algo.needs.skill interpolates it
    # (ablation_prior); null where the stage's own config says it.
    skill_prior: str | None = None
    # μ_g network and helper branch H hidden layers (ControlVAE: three of 256 for heading, 512 otherwise;
    # PhysicsVAE: task encoder (256, 128), helper (128, 128)).
    hidden: tuple[int, ...] = (256, 256, 256)
    helper_hidden: tuple[int, ...] = (128, 128)
    activation: str = "elu"
    # σ of the helper branch Δa = σ·tanh(H(s, z)); 0 turns it off (PhysicsVAE: 0.1 baseline, 1.0 rough terrain).
    sigma: float = 0.0
    # w_z on ‖μ_g‖², keeping the task policy near the prior (ControlVAE: 20).
    w_z: float = 20.0
    # The PPO trainer's reward: exp, e^(-L_g) (ControlVAE's) | progress, d_{t-1} − d_t, how much nearer the
    # root came to the target in the step (PhysicsVAE Sec. 5.2's point goal; point_goal and ppo only).
    reward: str = "exp"
    # Weights of the task's named terms and of the fall penalty.
    weights: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_WEIGHTS))
    # Root height below which L_fall grows (ControlVAE: 0.5 m).
    fall_height: float = 0.5
    # Synthetic rollouts: length T (ControlVAE 16) and number per update (256).
    rollout_steps: int = 16
    batch_size: int = 256
    # Sample z around its mean with the prior's std (Eq. 21's reparameterised Gaussian); false: the mean.
    latent_noise: bool = True
    # RAdam at lr · max(lr_decay^update, lr_floor) (ControlVAE §5.5: 0.001 · max(0.99^iteration, 0.1)).
    optimizer: str = "radam"
    lr: float = 1e-3
    lr_decay: float = 0.99
    lr_floor: float = 0.1
    grad_clip: float = 1.0
    # Goal changes per second within an episode (ControlVAE: every 72 control steps at its 20 Hz, 3.6 s).
    change_rate: float = 20.0 / 72.0
    # Simulated start states kept for the synthetic rollouts (ControlVAE's B_g: 4096).
    buffer_size: int = 4096

    def __post_init__(self) -> None:
        if self.task not in GOAL_DIMS:
            raise ValueError(f"task.task: unknown task {self.task!r}; expected one of {sorted(GOAL_DIMS)}")
        if self.trainer not in TRAINERS:
            raise ValueError(f"task.trainer: unknown trainer {self.trainer!r}; expected one of {TRAINERS}")
        if not 0 < self.lr_decay <= 1 or not 0 <= self.lr_floor <= 1:
            raise ValueError(
                f"task.lr_decay must be in (0, 1] and lr_floor in [0, 1], got {self.lr_decay}, {self.lr_floor}"
            )
        if self.change_rate < 0 or self.buffer_size < 1:
            raise ValueError("task.change_rate must be >= 0 and buffer_size >= 1")
        if self.sigma < 0:
            raise ValueError(f"task.sigma must be non-negative, got {self.sigma}")
        if self.reward not in TASK_REWARDS:
            raise ValueError(f"task.reward: unknown reward {self.reward!r}; expected one of {TASK_REWARDS}")
        if self.reward == "progress" and (self.task != "point_goal" or self.trainer != "ppo"):
            raise ValueError("task.reward: progress is the point goal's reward under the ppo trainer")
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
        prior_action: bool = True,
        device: torch.device | str = "cpu",
    ):
        self.config = c = config or TaskConfig()
        self.policy = task_policy(controller, action_dim, c, prior_action).to(device)
        optimizer = make_optimizer(c.optimizer, self.policy.parameters(), c.lr)
        super().__init__(self.policy, optimizer, c.grad_clip, device)
        if not isinstance(world_model, WorldModel):
            raise ValueError(
                "the model-based task trainer rolls out an integrating world model (world_model.kind=integrate)"
            )
        self.controller = controller.to(self.device).requires_grad_(False).eval()
        self.world_model = world_model.to(self.device).requires_grad_(False).eval()

    def set_frozen_weights(self, controller: Weights | None = None, world_model: Weights | None = None) -> None:
        if controller is not None:
            self.controller.load_state_dict(controller.state)
        if world_model is not None:
            self.world_model.load_state_dict(world_model.state)

    def before_update(self, batch: TaskBatch) -> None:
        c = self.config
        for group in self.optimizer.param_groups:
            group["lr"] = c.lr * max(c.lr_decay**self.version, c.lr_floor)
        self.policy.state_norm.update(body_state.features(self.tensor(batch.states)))

    def loss(self, batch: TaskBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        c = self.config
        bs, goals = self.tensor(batch.states), self.tensor(batch.goals)
        totals, reg = [], []
        sums: dict[str, torch.Tensor] = {}
        for t in range(goals.shape[1]):
            goal = goals[:, t]
            s = body_state.features(bs)
            eps = torch.randn(bs.shape[0], self.controller.latent_dim, device=bs.device) if c.latent_noise else None
            action, mu_g = self.policy(self.controller, s, goal_observation(c.task, bs, goal), eps)
            bs = self.world_model(bs, action, s)
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


def task_policy(controller: VAEController, action_dim: int, c: TaskConfig, prior_action: bool = True) -> TaskPolicy:
    """The task policy a TaskConfig describes, on `controller`'s state features and latent space."""
    return TaskPolicy(
        controller.state_norm.mean.shape[0],
        goal_observation_dim(c.task),
        controller.latent_dim,
        action_dim,
        c.hidden,
        c.helper_hidden,
        c.sigma,
        c.activation,
        prior_action,
    )


class GoalBuffer:
    """ControlVAE's B_g: the newest simulated states with the goals that followed each, as collected.

    `add` takes a collection's body states [T, M, B, 13] and goals [T, M, G]; `sample` draws start
    states and the recorded goal sequence of the next `steps` control steps from each (repeating the
    last goal where the collection ends sooner). The oldest collections go once more than
    `capacity` states are held.
    """

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.chunks: list[tuple[np.ndarray, np.ndarray]] = []

    def __len__(self) -> int:
        return sum(s.shape[0] * s.shape[1] for s, _ in self.chunks)

    def add(self, states: np.ndarray, goals: np.ndarray) -> None:
        self.chunks.append((np.asarray(states, np.float32), np.asarray(goals, np.float32)))
        while (
            len(self.chunks) > 1
            and len(self) - self.chunks[0][0].shape[0] * self.chunks[0][0].shape[1] >= self.capacity
        ):
            self.chunks.pop(0)

    def sample(self, n: int, steps: int, rng: np.random.Generator) -> TaskBatch:
        sizes = np.array([s.shape[0] * s.shape[1] for s, _ in self.chunks])
        if not sizes.sum():
            raise ValueError("the goal buffer is empty")
        flat = rng.integers(sizes.sum(), size=n)
        chunk = np.searchsorted(np.cumsum(sizes), flat, side="right")
        states, goals = [], []
        for k, i in zip(chunk, flat - np.concatenate(([0], np.cumsum(sizes)))[chunk], strict=True):
            s, g = self.chunks[k]
            t, m = divmod(int(i), s.shape[1])
            states.append(s[t, m])
            goals.append(g[np.minimum(t + np.arange(steps), s.shape[0] - 1), m])
        return TaskBatch(torch.from_numpy(np.stack(states)), torch.from_numpy(np.stack(goals)))

    def state_dict(self) -> dict:
        return {"chunks": [(s.copy(), g.copy()) for s, g in self.chunks]}

    def load_state_dict(self, state: dict) -> None:
        self.chunks = [(np.asarray(s, np.float32), np.asarray(g, np.float32)) for s, g in state["chunks"]]
