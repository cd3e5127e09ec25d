"""The VAE controller learner: one class, three objectives, three prior types (see `workers.models.vae`).

objective
  controlvae  The posterior tracks a reference clip in T-step rollouts through the
              frozen world model, starting from simulated states (ControlVAE Alg. 1).
              batch.states[:, 0] is the start, batch.reference the clip.
  physicsvae  Expert transitions: the decoder's action is cloned to the expert's and,
              with α > 0, pushed through the frozen world model to match the expert's
              next state (PhysicsVAE Eq. 1). batch.states and batch.actions are the expert's.
  pulse       Online distillation: the student's states, the reference as the goal
              s_g, the teacher's actions as labels (PULSE Eq. 3). batch.states,
              batch.reference and batch.actions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from workers.body.features import StateLayout
from workers.learners.base import Learner, Schedule, Weights, make_optimizer
from workers.losses.kl import gaussian_kl
from workers.losses.vae import PHYSICSVAE_REDUCTIONS, controlvae_loss, physicsvae_loss, pulse_loss
from workers.models import body_state
from workers.models.tracking_goal import GOALS, goal, goal_dim
from workers.models.vae import PRIOR_TYPES, VAEController
from workers.models.world_model import StateRegressor, WorldModel

OBJECTIVES = ("controlvae", "physicsvae", "pulse")


@dataclass
class VAEConfig:
    """What the three objectives share: the controller's networks and prior, the optimiser, the batches and β. A
    learner takes its objective's section (`OBJECTIVE_CONFIGS`: this with the terms of that loss); the networks
    alone (`build_controller`, the rollout policy) are built from any of them."""

    # Training objective: controlvae | physicsvae | pulse (each section's own, `OBJECTIVE_CONFIGS`).
    objective: str = "controlvae"
    # Prior over z: standard_normal | conditional | learned.
    prior: str = "conditional"
    # Latent size (ControlVAE 64, PhysicsVAE 32).
    latent_dim: int = 64
    # Prior and posterior MLPs (ControlVAE: two of 512, ELU, state re-concatenated at each layer).
    encoder_hidden: tuple[int, ...] = (512, 512)
    # Policy network: moe | mlp; each expert's (or the MLP's) hidden layers, number of experts, gate layers.
    policy: str = "moe"
    policy_hidden: tuple[int, ...] = (512, 512, 512)
    num_experts: int = 6
    gate_hidden: tuple[int, ...] = (64, 64)
    activation: str = "elu"
    # How the inputs meet the layers: concat (ControlVAE's: the conditioning re-concatenated at every layer
    # of prior, posterior and MLP policy, layer norm in the policy) | plain (PhysicsVAE's Table 2 and the
    # authors' code: the inputs concatenated once, plain MLPs). The moe policy is ControlVAE's either way.
    network: str = "concat"
    # σ_p, the fixed standard deviation of the conditional prior and its posterior (ControlVAE 0.3).
    sigma_p: float = 0.3
    # A fixed posterior standard deviation for the other priors; None learns it, except under the controlvae
    # objective with the standard normal prior, which is ControlVAE's VAE-NC (§5.6): posterior N(μ_q, I), so 1.0.
    posterior_std: float | None = None
    # Clamp of learned log-stds (PULSE clamps the prior's).
    log_std_min: float = -5.0
    log_std_max: float = 0.5
    # σ_π, the policy's action noise in synthetic rollouts (ControlVAE 0.05).
    action_noise: float = 0.05
    # Optimiser (ControlVAE: RAdam, lr 1e-5) and gradient-norm clip (0 disables).
    optimizer: str = "radam"
    lr: float = 1e-5
    grad_clip: float = 1.0
    # Trajectories per update (N_VAE 512) and their length (T_VAE 24).
    batch_size: int = 512
    rollout_steps: int = 24
    # β on the KL term: ControlVAE raises it from 0.01 to 0.1 every 500 epochs (8 updates each).
    beta: Schedule = field(default_factory=lambda: Schedule(0.01, 0.1, kind="staircase", steps=40_000, every=4_000))
    # What the posterior is given as the goal (workers/models/tracking_goal.py): reference (s̃_{t+1}, the reference's
    # next state in its own heading frame: ControlVAE's) | mimic (PULSE's s_g-mimic, §4.1: the reference's next
    # state as offsets from the character, which shows drift). mimic under the pulse objective only.
    goal: str = "reference"

    def __post_init__(self) -> None:
        if self.objective not in OBJECTIVES:
            raise ValueError(f"vae.objective: unknown objective {self.objective!r}; expected one of {OBJECTIVES}")
        if type(self) not in (VAEConfig, OBJECTIVE_CONFIGS[self.objective]):
            own = type(self).__dataclass_fields__["objective"].default
            raise ValueError(f"vae.objective: this section's objective is {own!r}, got {self.objective!r}")
        if self.prior not in PRIOR_TYPES:
            raise ValueError(f"vae.prior: unknown prior type {self.prior!r}; expected one of {PRIOR_TYPES}")
        if self.network not in ("concat", "plain"):
            raise ValueError(f"vae.network: unknown network {self.network!r}; expected 'concat' or 'plain'")
        if self.goal not in GOALS:
            raise ValueError(f"vae.goal: unknown goal {self.goal!r}; expected one of {GOALS}")
        if self.goal != "reference" and self.objective != "pulse":
            raise ValueError(
                f"vae.goal: {self.goal!r} is PULSE's goal; the {self.objective} objective takes 'reference'"
            )
        if self.objective == "physicsvae" and self.prior != "standard_normal":
            raise ValueError(
                f"vae.prior: the physicsvae objective has its KL to N(0, I) (PhysicsVAE Eq. 1), so the prior "
                f"must be standard_normal, got {self.prior!r}"
            )
        if self.objective == "controlvae" and self.prior == "standard_normal" and self.posterior_std is None:
            self.posterior_std = 1.0  # VAE-NC exactly: prior type alone varies, not the posterior's noise
        if self.posterior_std is not None and self.posterior_std <= 0:
            raise ValueError(f"vae.posterior_std must be positive, got {self.posterior_std}")
        if self.action_noise < 0:
            raise ValueError(f"vae.action_noise must be non-negative, got {self.action_noise}")
        if self.beta.start < 0 or (self.beta.end is not None and self.beta.end < 0):
            raise ValueError("vae.beta must be non-negative")

    def _non_negative(self, *keys: str) -> None:
        for key in keys:
            if getattr(self, key) < 0:
                raise ValueError(f"vae.{key} must be non-negative, got {getattr(self, key)}")


@dataclass
class ControlVAEObjective(VAEConfig):
    """The controlvae objective's section: Eq. 16's reconstruction through the world model, Eq. 12's action terms."""

    objective: str = "controlvae"
    # Discount of the rollout losses (ControlVAE 0.95).
    gamma: float = 0.95
    # Action regularisation of Eq. 12: L1 and squared-L2 weights.
    w_a1: float = 0.0
    w_a2: float = 0.01
    # W of Eq. 16, by part of s: body positions, 6D rotations, velocities, angular velocities, heights, root up
    # (also the weights of Eq. 20's tracking reward that the rollout workers record).
    state_weights: dict[str, float] = field(
        default_factory=lambda: {"pos": 1.0, "rot": 1.0, "lin_vel": 0.1, "ang_vel": 0.05, "height": 1.0, "up": 1.0}
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        self._non_negative("w_a1", "w_a2")
        if not 0 < self.gamma <= 1:
            raise ValueError(f"vae.gamma must be in (0, 1], got {self.gamma}")


@dataclass
class PhysicsVAEObjective(VAEConfig):
    """The physicsvae objective's section: Eq. 1's behaviour cloning and α-weighted simulation consistency."""

    objective: str = "physicsvae"
    # Eq. 1's KL is to N(0, I): the only prior this objective takes.
    prior: str = "standard_normal"
    # α, PhysicsVAE's simulation-consistency weight (Table 1: 1e-4).
    alpha: float = 1e-4
    # How PhysicsVAE's Eq. 1 reduces its squared errors over the action and state dimensions: mean, averaged over
    # the 28 action and 243 state dimensions with the KL summed over the latent (the authors' trainer's
    # nn.MSELoss, with which Table 1's α and β and Fig. 9's α axis were set) | sum (Eq. 1 as printed: α then
    # weighs the state term 243/28 = 8.7x more, β 28x less).
    physicsvae_reduction: str = "mean"

    def __post_init__(self) -> None:
        super().__post_init__()
        self._non_negative("alpha")
        if self.physicsvae_reduction not in PHYSICSVAE_REDUCTIONS:
            raise ValueError(
                f"vae.physicsvae_reduction: unknown reduction {self.physicsvae_reduction!r}; "
                f"expected one of {PHYSICSVAE_REDUCTIONS}"
            )


@dataclass
class PulseObjective(VAEConfig):
    """The pulse objective's section: Eq. 3's distillation with its latent smoothness term."""

    objective: str = "pulse"
    # λ on PULSE's latent smoothness L_regu.
    lambda_regu: float = 0.01

    def __post_init__(self) -> None:
        super().__post_init__()
        self._non_negative("lambda_regu")


# Each objective's section: the terms of its loss beside what every objective shares (`VAEConfig`).
OBJECTIVE_CONFIGS: dict[str, type[VAEConfig]] = {
    "controlvae": ControlVAEObjective,
    "physicsvae": PhysicsVAEObjective,
    "pulse": PulseObjective,
}


def vae_config(objective: str = "controlvae", **settings: Any) -> VAEConfig:
    """The section of `objective` with `settings`."""
    if objective not in OBJECTIVE_CONFIGS:
        raise ValueError(f"vae.objective: unknown objective {objective!r}; expected one of {OBJECTIVES}")
    return OBJECTIVE_CONFIGS[objective](**settings)


@dataclass
class VAEBatch:
    """states [N, T+1, B, 13]; reference [N, T+1, B, 13] (controlvae, pulse); actions [N, T, A]
    (the expert's for physicsvae, the teacher's for pulse)."""

    states: torch.Tensor | np.ndarray
    reference: torch.Tensor | np.ndarray | None = None
    actions: torch.Tensor | np.ndarray | None = None
    # [k, B, 13] states that feed the state normaliser instead of `states` (single-state starts).
    norm_states: torch.Tensor | np.ndarray | None = None
    # [N, T+1, D] the features s of `states`, where the caller has them (physicsvae: a fixed dataset computes them
    # once); None computes them here.
    features: torch.Tensor | np.ndarray | None = None


def state_weight_vector(num_bodies: int, weights: dict[str, float]) -> torch.Tensor:
    """W of Eq. 16 as a weight per feature [16·B + 3]."""
    layout = StateLayout(num_bodies)
    w = torch.zeros(layout.dim)
    for part in ("pos", "rot", "lin_vel", "ang_vel", "height", "up"):
        w[getattr(layout, part)] = weights[part]
    return w


def build_controller(num_bodies: int, action_dim: int, config: VAEConfig) -> VAEController:
    """The networks a VAEConfig describes (learners, rollout workers and evaluation build them alike)."""
    c = config
    return VAEController(
        StateLayout(num_bodies).dim,
        action_dim,
        prior=c.prior,
        latent_dim=c.latent_dim,
        encoder_hidden=c.encoder_hidden,
        policy=c.policy,
        policy_hidden=c.policy_hidden,
        num_experts=c.num_experts,
        gate_hidden=c.gate_hidden,
        act=c.activation,
        sigma_p=c.sigma_p,
        posterior_std=c.posterior_std,
        log_std_range=(c.log_std_min, c.log_std_max),
        plain=c.network == "plain",
        goal=c.goal,
        goal_dim=None if c.goal == "reference" else goal_dim(c.goal, num_bodies),
    )


class VAELearner(Learner):
    name = "vae"

    def __init__(
        self,
        num_bodies: int,
        action_dim: int,
        config: VAEConfig | None = None,
        world_model: WorldModel | StateRegressor | None = None,
        seed: int = 0,
        device: torch.device | str = "cpu",
    ):
        self.config = c = config or ControlVAEObjective()
        if not isinstance(c, OBJECTIVE_CONFIGS[c.objective]):
            raise TypeError(f"the {c.objective} objective's learner takes a {OBJECTIVE_CONFIGS[c.objective].__name__}")
        self.action_dim = action_dim
        self.vae = build_controller(num_bodies, action_dim, c).to(device)
        optimizer = make_optimizer(c.optimizer, self.vae.parameters(), c.lr)
        super().__init__(self.vae, optimizer, c.grad_clip, device)
        needs_model = c.objective == "controlvae" or (c.objective == "physicsvae" and c.alpha > 0)
        if needs_model and world_model is None:
            raise ValueError(f"the {c.objective} objective needs a world model")
        if c.objective == "controlvae" and world_model is not None and not isinstance(world_model, WorldModel):
            raise ValueError(
                "the controlvae objective rolls out an integrating world model (world_model.kind=integrate)"
            )
        self.world_model = world_model
        if world_model is not None:
            world_model.to(self.device).requires_grad_(False)
            world_model.eval()
        if isinstance(c, ControlVAEObjective):
            self.state_weights = state_weight_vector(num_bodies, c.state_weights).to(self.device)
        self.generator = torch.Generator(device=self.device).manual_seed(seed)

    def set_world_model_weights(self, weights: Weights) -> None:
        """Load the world-model learner's published weights into the frozen copy."""
        self.world_model.load_state_dict(weights.state)

    @property
    def beta(self) -> float:
        return self.config.beta(self.version)

    def before_update(self, batch: VAEBatch) -> None:
        if batch.norm_states is None and batch.features is not None:
            self.vae.state_norm.update(self.tensor(batch.features))
        else:
            states = batch.states if batch.norm_states is None else batch.norm_states
            self.vae.state_norm.update(body_state.features(self.tensor(states)))
        if self.vae.goal_norm is not None:  # the goals the pulse objective will give the posterior
            self.vae.goal_norm.update(self._goals(self.tensor(batch.states), self.tensor(batch.reference)))

    def loss(
        self, batch: VAEBatch, draws: tuple[torch.Tensor, ...] | None = None, beta: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The objective's loss and terms. Its standard-normal draws (latent samples, action noise) come from
        the learner's generator as it goes and β from its schedule at this update, or, given `draws` and
        `beta` (`loss_inputs`), from those."""
        objective = self.config.objective
        states = self.tensor(batch.states)
        drawn = iter(draws) if draws is not None else None
        beta = self.beta if beta is None else beta

        def randn(shape: torch.Size) -> torch.Tensor:
            return torch.randn(shape, generator=self.generator, device=self.device) if drawn is None else next(drawn)

        if objective == "controlvae":
            total, terms = self._controlvae(states, self.tensor(batch.reference), randn, beta)
        elif objective == "physicsvae":
            features = None if batch.features is None else self.tensor(batch.features)
            total, terms = self._physicsvae(states, self.tensor(batch.actions), randn, beta, features)
        else:
            total, terms = self._pulse(states, self.tensor(batch.reference), self.tensor(batch.actions), randn, beta)
        terms["beta"] = torch.as_tensor(beta)
        return total, terms

    def loss_inputs(self, batch: VAEBatch) -> dict[str, Any]:
        """The standard-normal draws `loss(batch)` makes, in its order and from the same generator, drawn ahead,
        and this update's β as a tensor: a compiled loss is given them, so that it sees the same numbers."""
        n, steps = batch.states.shape[0], batch.states.shape[1] - 1
        z, a = self.config.latent_dim, self.action_dim
        if self.config.objective == "controlvae":  # per step: the latent sample, then the action noise
            shapes = [(n, z), (n, a)] * (batch.reference.shape[1] - 1)
        else:
            shapes = [(n, steps, z)]
        draws = tuple(torch.randn(shape, generator=self.generator, device=self.device) for shape in shapes)
        return {"draws": draws, "beta": torch.tensor(self.beta, device=self.device)}

    def _controlvae(self, states: torch.Tensor, reference: torch.Tensor, randn, beta):
        c = self.config
        ref_features = body_state.features(reference)  # [N, T+1, D]
        bs = states[:, 0]
        s = body_state.features(bs)
        predicted, kls, actions = [], [], []
        for t in range(reference.shape[1] - 1):
            q, p = self.vae.encode(s, ref_features[:, t + 1])
            a = self.vae.act(s, q.rsample(eps=randn(q.mean.shape)))
            bs = self.world_model(bs, a + randn(a.shape) * c.action_noise, s)
            s = body_state.features(bs)  # the prediction the loss compares, and the next step's state
            predicted.append(s)
            kls.append(gaussian_kl(q.mean, q.log_std, p.mean, p.log_std))
            actions.append(a)
        return controlvae_loss(
            torch.stack(predicted, 1),
            ref_features[:, 1:],
            torch.stack(kls, 1),
            torch.stack(actions, 1),
            self.state_weights,
            c.gamma,
            beta,
            c.w_a1,
            c.w_a2,
        )

    def _physicsvae(self, states: torch.Tensor, expert_actions: torch.Tensor, randn, beta, features=None):
        s = body_state.features(states) if features is None else features  # [N, T+1, D]
        q, p = self.vae.encode(s[:, :-1], s[:, 1:])
        a = self.vae.act(s[:, :-1], q.rsample(eps=randn(q.mean.shape)))
        if self.config.alpha > 0:
            predicted_next = self.world_model.next_features(states[:, :-1], a, s[:, :-1])
        else:
            predicted_next = s[:, 1:]
        kl = gaussian_kl(q.mean, q.log_std, p.mean, p.log_std)
        c = self.config
        return physicsvae_loss(a, expert_actions, predicted_next, s[:, 1:], kl, c.alpha, beta, c.physicsvae_reduction)

    def _goals(self, states: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
        """The goal [N, T, G] of each state states[:, t] toward the reference's next state reference[:, t + 1]."""
        return goal(self.config.goal, states[:, :-1], reference[:, 1:])

    def _pulse(self, states: torch.Tensor, reference: torch.Tensor, teacher_actions: torch.Tensor, randn, beta):
        s = body_state.features(states[:, :-1])
        q, p = self.vae.encode(s, self._goals(states, reference))
        a = self.vae.act(s, q.rsample(eps=randn(q.mean.shape)))
        kl = gaussian_kl(q.mean, q.log_std, p.mean, p.log_std)
        return pulse_loss(a, teacher_actions, q.mean, kl, self.config.lambda_regu, beta)
