"""The VAE controller's networks: prior p(z | s), posterior q(z | s, s'), policy π(a | s, z).

Prior types (config `prior`):
  standard_normal  p = N(0, I), the posterior N(μ_q(s, s'), σ_q²) stands alone
                   (PhysicsVAE; ControlVAE's VAE-NC).
  conditional      p = N(μ_p(s), σ_p² I) with fixed σ_p, and the posterior is its
                   residual, N(μ_p(s) + μ_q(s, s'), σ_p² I) (ControlVAE Eq. 8–9).
  learned          p = N(μ_p(s), σ_p(s)²) with a learned, clamped log-std, the
                   posterior a residual on its mean with its own log-std (PULSE).
σ_q is learned unless `posterior_std` fixes it (1.0 gives ControlVAE's VAE-NC exactly).

The prior and posterior MLPs re-concatenate their conditioning state at every
layer (ControlVAE §3.4.1). The policy is an MLP or a mixture of experts whose
parameters are blended per sample by a gating network, z concatenated to every
expert layer's input with layer norm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from workers.models.nets import ConcatMLP, Normalizer, PlainMLP, activation, mlp

PRIOR_TYPES = ("standard_normal", "conditional", "learned")


class Gaussian:
    """A diagonal Gaussian as (mean, log-std), both [..., Z]."""

    def __init__(self, mean: torch.Tensor, log_std: torch.Tensor):
        self.mean = mean
        self.log_std = log_std.expand_as(mean)

    def rsample(self, generator: torch.Generator | None = None, eps: torch.Tensor | None = None) -> torch.Tensor:
        """mean + std · eps, with eps standard normal: from `generator`, or given."""
        if eps is None:
            eps = torch.randn(self.mean.shape, generator=generator, dtype=self.mean.dtype, device=self.mean.device)
        return self.mean + self.log_std.exp() * eps


class Prior(nn.Module):
    def __init__(
        self,
        kind: str,
        state_dim: int,
        latent_dim: int,
        hidden: Sequence[int] = (512, 512),
        act: str = "elu",
        sigma_p: float = 0.3,
        log_std_range: tuple[float, float] = (-5.0, 0.5),
        plain: bool = False,
    ):
        super().__init__()
        if kind not in PRIOR_TYPES:
            raise ValueError(f"unknown prior type {kind!r}; expected one of {PRIOR_TYPES}")
        self.kind = kind
        self.latent_dim = latent_dim
        self.log_sigma_p = math.log(sigma_p)
        self.log_std_range = log_std_range
        out = 2 * latent_dim if kind == "learned" else latent_dim
        if kind == "standard_normal":
            self.net = None
        elif plain:  # s once, at the input
            self.net = mlp(state_dim, hidden, out, act)
        else:
            self.net = ConcatMLP(state_dim, state_dim, hidden, out, act)
        self.plain = plain

    def forward(self, s: torch.Tensor) -> Gaussian:
        """p(z | s) for normalised features s [..., D]."""
        if self.net is None:
            zero = s.new_zeros(s.shape[:-1] + (self.latent_dim,))
            return Gaussian(zero, zero)
        out = self.net(s) if self.plain else self.net(s, s)
        if self.kind == "conditional":
            return Gaussian(out, out.new_full((), self.log_sigma_p))
        mean, log_std = out.chunk(2, dim=-1)
        return Gaussian(mean, log_std.clamp(*self.log_std_range))


class Posterior(nn.Module):
    def __init__(
        self,
        kind: str,
        state_dim: int,
        latent_dim: int,
        hidden: Sequence[int] = (512, 512),
        act: str = "elu",
        sigma_p: float = 0.3,
        posterior_std: float | None = None,
        log_std_range: tuple[float, float] = (-5.0, 0.5),
        plain: bool = False,
        goal_dim: int | None = None,
    ):
        super().__init__()
        self.kind = kind
        self.plain = plain
        goal_dim = state_dim if goal_dim is None else goal_dim
        self.latent_dim = latent_dim
        self.log_std_range = log_std_range
        if kind == "conditional":
            self.fixed_log_std = math.log(sigma_p)
        else:
            self.fixed_log_std = None if posterior_std is None else math.log(posterior_std)
        out = latent_dim if self.fixed_log_std is not None else 2 * latent_dim
        if plain:
            self.net = PlainMLP(state_dim, goal_dim, hidden, out, act)
        else:
            self.net = ConcatMLP(state_dim + goal_dim, goal_dim, hidden, out, act)

    def forward(self, s: torch.Tensor, goal: torch.Tensor, prior: Gaussian) -> Gaussian:
        """q(z | s, g) for normalised features s [..., D] and goal g [..., G] (s' by default); a residual on the
        prior mean."""
        out = self.net(s, goal) if self.plain else self.net(torch.cat((s, goal), dim=-1), goal)
        if self.fixed_log_std is not None:
            mean, log_std = out, out.new_full((), self.fixed_log_std)
        else:
            mean, log_std = out.chunk(2, dim=-1)
            log_std = log_std.clamp(*self.log_std_range)
        return Gaussian(prior.mean + mean, log_std)


class MixtureOfExperts(nn.Module):
    """a = Σ_k g_k(s, z) · expert_k(s, z), blending the experts' parameters layer by layer.

    Blending the weights of a linear layer and applying them equals blending the
    layer's outputs for the same input, so each layer runs every expert on one
    shared input and mixes the results before the activation.
    """

    def __init__(
        self,
        state_dim: int,
        latent_dim: int,
        action_dim: int,
        num_experts: int = 6,
        hidden: Sequence[int] = (512, 512, 512),
        gate_hidden: Sequence[int] = (64, 64),
        act: str = "elu",
    ):
        super().__init__()
        self.gate = mlp(state_dim + latent_dim, gate_hidden, num_experts, act)
        dims = [state_dim, *hidden, action_dim]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        self.norms = nn.ModuleList()
        for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
            fan_in = d_in + latent_dim
            bound = 1.0 / math.sqrt(fan_in)
            scale = 0.01 if i == len(dims) - 2 else 1.0
            self.weights.append(nn.Parameter(torch.empty(num_experts, fan_in, d_out).uniform_(-bound, bound) * scale))
            self.biases.append(nn.Parameter(torch.zeros(num_experts, d_out)))
            self.norms.append(nn.LayerNorm(fan_in))
        self.act = activation(act)

    def forward(self, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        lead = s.shape[:-1]
        s, z = s.reshape(-1, s.shape[-1]), z.reshape(-1, z.shape[-1])
        g = torch.softmax(self.gate(torch.cat((s, z), dim=-1)), dim=-1)  # [N, K]
        h = s
        last = len(self.weights) - 1
        for i, (w, b, norm) in enumerate(zip(self.weights, self.biases, self.norms, strict=True)):
            x = norm(torch.cat((h, z), dim=-1))
            per_expert = torch.einsum("ni,kio->nko", x, w) + b  # [N, K, out]
            h = torch.einsum("nk,nko->no", g, per_expert)
            if i < last:
                h = self.act(h)
        return h.reshape(lead + (h.shape[-1],))


class MLPPolicy(nn.Module):
    """μ_π(s, z): z re-concatenated at every layer with layer norm (ours), or with `plain` (s, z) once at the
    input of a plain MLP (PhysicsVAE's motor decoder)."""

    def __init__(
        self, state_dim: int, latent_dim: int, action_dim: int, hidden: Sequence[int], act: str = "elu",
        plain: bool = False,
    ):  # fmt: skip
        super().__init__()
        if plain:
            self.net = PlainMLP(state_dim, latent_dim, hidden, action_dim, act, out_scale=0.01)
        else:
            self.net = ConcatMLP(state_dim, latent_dim, hidden, action_dim, act, layer_norm=True, out_scale=0.01)

    def forward(self, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return self.net(s, z)


class VAEController(nn.Module):
    """Prior, posterior and policy over one shared state normaliser.

    All methods take raw features s [..., D] (`workers.models.body_state.features`).
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        prior: str = "conditional",
        latent_dim: int = 64,
        encoder_hidden: Sequence[int] = (512, 512),
        policy: str = "moe",
        policy_hidden: Sequence[int] = (512, 512, 512),
        num_experts: int = 6,
        gate_hidden: Sequence[int] = (64, 64),
        act: str = "elu",
        sigma_p: float = 0.3,
        posterior_std: float | None = None,
        log_std_range: tuple[float, float] = (-5.0, 0.5),
        plain: bool = False,
        goal: str = "reference",
        goal_dim: int | None = None,
    ):
        super().__init__()
        self.latent_dim = latent_dim
        self.goal = goal  # what the posterior is given (`workers.models.tracking_goal`); "reference" is s̃_{t+1}
        self.state_norm = Normalizer(state_dim)
        # A goal of its own size has its own normaliser; s' shares the state's.
        self.goal_norm = Normalizer(goal_dim) if goal_dim is not None else None
        self.prior = Prior(prior, state_dim, latent_dim, encoder_hidden, act, sigma_p, log_std_range, plain)
        self.posterior = Posterior(
            prior, state_dim, latent_dim, encoder_hidden, act, sigma_p, posterior_std, log_std_range, plain, goal_dim
        )
        if policy == "moe":
            self.policy = MixtureOfExperts(
                state_dim, latent_dim, action_dim, num_experts, policy_hidden, gate_hidden, act
            )
        elif policy == "mlp":
            self.policy = MLPPolicy(state_dim, latent_dim, action_dim, policy_hidden, act, plain)
        else:
            raise ValueError(f"unknown policy type {policy!r}; expected 'mlp' or 'moe'")

    def prior_dist(self, s: torch.Tensor) -> Gaussian:
        return self.prior(self.state_norm(s))

    def encode(self, s: torch.Tensor, goal: torch.Tensor) -> tuple[Gaussian, Gaussian]:
        """(posterior q(z | s, g), prior p(z | s)); the goal g is s' unless the controller was built with another."""
        sn = self.state_norm(s)
        p = self.prior(sn)
        gn = self.state_norm(goal) if self.goal_norm is None else self.goal_norm(goal)
        return self.posterior(sn, gn, p), p

    def act(self, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """The policy's mean action μ_π(s, z) [..., A]."""
        return self.policy(self.state_norm(s), z)

    def task_latent(self, s: torch.Tensor, z_task: torch.Tensor, prior_action: bool) -> torch.Tensor:
        """The latent a downstream task policy's output `z_task` stands for: with `prior_action`, a residual on
        the prior's mean, z = z_task + μ_p(s) (PULSE Eq. 4, ControlVAE Eq. 21); without, z_task itself."""
        return z_task + self.prior_dist(s).mean if prior_action else z_task
