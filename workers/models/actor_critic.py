"""A Gaussian policy with a fixed action std and a separate value function, as in AMP (Peng et al. 2021, Sec. 6.2).

π(a | s) = N(μ(s), diag(σ²)) with μ an MLP and σ fixed (a buffer, never trained);
V(s) a second MLP of its own. Both read the observation through one running
`Normalizer`, whose statistics the learner updates. Log-probabilities and
entropies are summed over action dimensions: shapes [..., obs_dim] -> [...].
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.distributions import Normal

from workers.models.nets import Normalizer, mlp


class ActorCritic(nn.Module):
    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        action_std: float | Sequence[float],
        policy_hidden: Sequence[int] = (1024, 512),
        value_hidden: Sequence[int] = (1024, 512),
        activation: str = "relu",
        policy_out_scale: float = 0.01,
        obs_norm_max_count: float = 1e6,
    ):
        """action_std: σ, one value for every action dimension or one per dimension.
        policy_out_scale: initial scale of the policy's last layer (its bias starts at zero),
        so the initial mean action is close to zero.
        """
        super().__init__()
        std = torch.as_tensor(action_std, dtype=torch.float32).expand(act_dim).clone()
        if not bool((std > 0).all()):
            raise ValueError(f"action_std must be positive, got {action_std}")
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.obs_norm = Normalizer(obs_dim, max_count=obs_norm_max_count)
        self.policy = mlp(obs_dim, policy_hidden, act_dim, activation, out_scale=policy_out_scale)
        self.critic = mlp(obs_dim, value_hidden, 1, activation)
        self.register_buffer("action_std", std)

    def mean(self, obs: torch.Tensor) -> torch.Tensor:
        """[..., obs_dim] -> [..., act_dim] μ(s)."""
        return self.policy(self.obs_norm(obs))

    def dist(self, obs: torch.Tensor) -> Normal:
        """The per-dimension Normal over actions; batch shape [..., act_dim]."""
        mean = self.mean(obs)
        return Normal(mean, self.action_std.to(mean.dtype).expand_as(mean))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """[..., obs_dim] -> [...] V(s)."""
        return self.critic(self.obs_norm(obs)).squeeze(-1)

    def log_prob(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """[..., obs_dim], [..., act_dim] -> [...] log π(a | s)."""
        return self.dist(obs).log_prob(action).sum(-1)

    def entropy(self) -> torch.Tensor:
        """Scalar entropy of the policy; a constant, since σ is fixed."""
        return (0.5 + 0.5 * torch.log(2 * torch.pi * self.action_std**2)).sum()

    @torch.no_grad()
    def act(
        self, obs: torch.Tensor, deterministic: bool = False, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """[..., obs_dim] -> (action [..., act_dim], log π(action | s) [...]).

        deterministic: return the mean action (its log-probability is still reported).
        generator: the source of the Gaussian noise, for reproducible sampling.
        """
        mean = self.mean(obs)
        std = self.action_std.to(mean.dtype)
        if deterministic:
            noise = torch.zeros_like(mean)
        else:
            noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
        # log N(μ + σε; μ, σ) = −ε²/2 − log σ − log √(2π), from the noise itself: the same number
        # as Normal.log_prob up to rounding, without building a distribution for every step.
        log_prob = (-0.5 * noise.square() - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        return mean + std * noise, log_prob
