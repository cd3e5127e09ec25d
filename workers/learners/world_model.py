"""The world-model learner: T_w-step synthetic rollouts from recorded trajectories (ControlVAE §3.3.2)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from workers.learners.base import Learner, make_optimizer
from workers.losses.world_model import regression_loss, world_model_loss
from workers.models import body_state
from workers.models.world_model import StateRegressor, WorldModel

WORLD_MODEL_KINDS = ("integrate", "regress")


@dataclass
class WorldModelConfig:
    # integrate: ControlVAE's model, velocity changes integrated into the next body state, trained on
    # T_w-step rollouts by Eq. 17 | regress: PhysicsVAE's simulation layer as Table 2 and the authors' code
    # have it, a plain MLP from (s, a) to s′ trained by MSE on single transitions (no rollouts).
    kind: str = "integrate"
    # Hidden layer sizes of the MLP (ControlVAE: four of 512, ELU).
    hidden: tuple[int, ...] = (512, 512, 512, 512)
    activation: str = "elu"
    # How positions and rotations follow the predicted velocities: euler | semi_implicit | midpoint.
    integrator: str = "semi_implicit"
    # Optimiser and learning rate (ControlVAE: 2e-3 for the world model).
    optimizer: str = "adam"
    lr: float = 2e-3
    # Steps of each synthetic rollout, T_w (ControlVAE: 8) and trajectories per update, N_w (512).
    rollout_steps: int = 8
    batch_size: int = 512
    # Gradient-norm clip; 0 disables.
    grad_clip: float = 1.0
    # W' of Eq. 17: weights of the position, rotation, linear and angular velocity errors.
    weights: dict[str, float] = field(default_factory=lambda: {"pos": 1.0, "rot": 1.0, "lin_vel": 0.2, "ang_vel": 0.05})

    def __post_init__(self) -> None:
        if self.kind not in WORLD_MODEL_KINDS:
            raise ValueError(f"world_model.kind: unknown kind {self.kind!r}; expected one of {WORLD_MODEL_KINDS}")
        if self.kind == "regress" and self.rollout_steps != 1:
            raise ValueError(
                f"world_model.rollout_steps: a regress layer learns single transitions, got {self.rollout_steps}"
            )
        if self.rollout_steps < 1:
            raise ValueError(f"world_model.rollout_steps must be at least 1, got {self.rollout_steps}")
        if self.lr <= 0:
            raise ValueError(f"world_model.lr must be positive, got {self.lr}")


def build_world_model(
    num_bodies: int, action_dim: int, config: WorldModelConfig, dt: float
) -> WorldModel | StateRegressor:
    """The network a WorldModelConfig describes, predicting dt seconds (one control step) ahead: the
    learner's, and the frozen copies the VAE and task learners are given, are built alike."""
    if config.kind == "regress":
        return StateRegressor(num_bodies, action_dim, config.hidden, config.activation)
    return WorldModel(num_bodies, action_dim, config.hidden, config.activation, dt, config.integrator)


@dataclass
class WorldModelBatch:
    """Recorded trajectories: body states [N, T+1, B, 13] and the actions between them [N, T, A]; `features`
    [N, T+1, D], the states' s, where the caller has them (a fixed dataset computes them once)."""

    states: torch.Tensor
    actions: torch.Tensor
    features: torch.Tensor | None = None


class WorldModelLearner(Learner):
    name = "world_model"

    def __init__(
        self,
        num_bodies: int,
        action_dim: int,
        dt: float,
        config: WorldModelConfig | None = None,
        device: torch.device | str = "cpu",
    ):
        self.config = config or WorldModelConfig()
        c = self.config
        self.model = build_world_model(num_bodies, action_dim, c, dt).to(device)
        optimizer = make_optimizer(c.optimizer, self.model.parameters(), c.lr)
        super().__init__(self.model, optimizer, c.grad_clip, device)

    def _tensors(self, batch: WorldModelBatch) -> tuple[torch.Tensor, torch.Tensor]:
        states, actions = self.tensor(batch.states), self.tensor(batch.actions)
        if states.shape[1] != actions.shape[1] + 1:
            raise ValueError(f"states have {states.shape[1]} steps, actions {actions.shape[1]}: need T+1 and T")
        return states, actions

    def before_update(self, batch: WorldModelBatch) -> None:
        states, actions = self._tensors(batch)
        self.model.observe(states[:, :-1], actions, states[:, 1:])

    def loss(self, batch: WorldModelBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        states, actions = self._tensors(batch)
        if self.config.kind == "regress":
            s = body_state.features(states) if batch.features is None else self.tensor(batch.features)
            return regression_loss(self.model.next_features(states[:, :-1], actions, s[:, :-1]), s[:, 1:])
        predicted = self.model.rollout(states[:, 0], actions)
        return world_model_loss(predicted, states[:, 1:], self.config.weights)

    @torch.no_grad()
    def predict(self, start: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Open-loop prediction [N, T, B, 13] (eval mode, no gradient)."""
        self.model.eval()
        return self.model.rollout(self.tensor(start), self.tensor(actions))
