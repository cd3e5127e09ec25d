"""A Gaussian policy with a fixed action std and a separate value function, as in AMP (Peng et al. 2021, Sec. 6.2).

π(a | s) = N(μ(s), diag(σ²)) with μ an MLP and σ fixed (a buffer, never trained);
V(s) a second MLP of its own. Both read the observation through one running
`Normalizer`, whose statistics the learner updates. Log-probabilities and
entropies are summed over action dimensions: shapes [..., obs_dim] -> [...].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torch.distributions import Normal

from workers.models.nets import Normalizer, gaussian, mlp


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

    def dist(self, obs: torch.Tensor, action: torch.Tensor | None = None) -> Normal:
        """The per-dimension Normal over actions; batch shape [..., act_dim]. `action`, the action taken, is
        for policies whose later dimensions are conditioned on earlier ones (`HelperActorCritic`): the
        Normal's log_prob at that action is then the policy's."""
        mean = self.mean(obs)
        return Normal(mean, self.action_std.to(mean.dtype).expand_as(mean))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """[..., obs_dim] -> [...] V(s)."""
        return self.critic(self.obs_norm(obs)).squeeze(-1)

    def log_prob(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """[..., obs_dim], [..., act_dim] -> [...] log π(a | s)."""
        return self.dist(obs, action).log_prob(action).sum(-1)

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
            noise = gaussian(mean.shape, generator, mean.dtype, mean.device)
        # log N(μ + σε; μ, σ) = −ε²/2 − log σ − log √(2π), from the noise itself: the same number
        # as Normal.log_prob up to rounding, without building a distribution for every step.
        log_prob = (-0.5 * noise.square() - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        return mean + std * noise, log_prob


@dataclass(frozen=True)
class HelperLayout:
    """The sizes a `HelperActorCritic` splits its observation (s, g, b) and action (u_z, u_h) into."""

    state_dim: int
    goal_dim: int
    latent_dim: int
    action_dim: int
    hidden: tuple[int, ...] = (128, 128)  # H's hidden layers (PhysicsVAE Table 2: 128, 128)

    @property
    def obs_dim(self) -> int:
        return self.state_dim + self.goal_dim + self.latent_dim

    @property
    def act_dim(self) -> int:
        return self.latent_dim + self.action_dim


class HelperActorCritic(ActorCritic):
    """A task policy with PhysicsVAE's helper branch (Eq. 2) as PPO trains it: the action is (u_z, u_h), the
    latent offset [Z] and the helper's pre-activation [A], drawn one after the other,

        u_z ~ N(μ_g(s, g), σ²),   z = b + u_z,   u_h ~ N(H(s, z), σ²),

    so that the helper reads the latent the decoder is given, H(s_t, z_t), not the goal. The observation is
    (s [D], g [G], b [Z]), b being the latent u_z is added to (the prior's mean μ_p(s) with the prior-action,
    else 0): μ_g reads (s, g) and H reads (s, z), s through the shared normaliser. log π(u) is the sum of
    both Gaussians' log densities, which `dist(obs, action)` gives at the taken action.
    """

    def __init__(
        self,
        state_dim: int,
        goal_dim: int,
        latent_dim: int,
        action_dim: int,
        action_std: float | Sequence[float],
        policy_hidden: Sequence[int] = (1024, 512),
        value_hidden: Sequence[int] = (1024, 512),
        helper_hidden: Sequence[int] = (128, 128),
        activation: str = "relu",
        policy_out_scale: float = 0.01,
        obs_norm_max_count: float = 1e6,
    ):
        obs_dim = state_dim + goal_dim + latent_dim
        super().__init__(
            obs_dim, latent_dim + action_dim, action_std, policy_hidden, value_hidden, activation, policy_out_scale,
            obs_norm_max_count,
        )  # fmt: skip
        self.state_dim, self.goal_dim, self.latent_dim = state_dim, goal_dim, latent_dim
        latent = mlp(state_dim + goal_dim, policy_hidden, latent_dim, activation, out_scale=policy_out_scale)
        helper = mlp(state_dim + latent_dim, helper_hidden, action_dim, activation, out_scale=policy_out_scale)
        self.policy = nn.ModuleDict({"latent": latent, "helper": helper})

    def _latent_mean(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(normalised s, μ_g) of observations [..., obs_dim]."""
        n = self.obs_norm(obs)
        return n[..., : self.state_dim], self.policy["latent"](n[..., : self.state_dim + self.goal_dim])

    def _helper_mean(self, obs: torch.Tensor, s_norm: torch.Tensor, u_z: torch.Tensor) -> torch.Tensor:
        z = obs[..., self.state_dim + self.goal_dim :] + u_z
        return self.policy["helper"](torch.cat((s_norm, z), dim=-1))

    def mean(self, obs: torch.Tensor, action: torch.Tensor | None = None) -> torch.Tensor:
        """(μ_g, H(s, b + u_z)) [..., Z + A], u_z the taken action's first part, or μ_g when none is given
        (the deterministic action)."""
        s_norm, mu_z = self._latent_mean(obs)
        u_z = mu_z if action is None else action[..., : self.latent_dim]
        return torch.cat((mu_z, self._helper_mean(obs, s_norm, u_z)), dim=-1)

    def dist(self, obs: torch.Tensor, action: torch.Tensor | None = None) -> Normal:
        mean = self.mean(obs, action)
        return Normal(mean, self.action_std.to(mean.dtype).expand_as(mean))

    @torch.no_grad()
    def act(
        self, obs: torch.Tensor, deterministic: bool = False, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        s_norm, mu_z = self._latent_mean(obs)
        std = self.action_std.to(mu_z.dtype)
        std_z, std_h = std[: self.latent_dim], std[self.latent_dim :]

        def noise(like: torch.Tensor) -> torch.Tensor:
            if deterministic:
                return torch.zeros_like(like)
            return gaussian(like.shape, generator, like.dtype, like.device)

        eps_z = noise(mu_z)
        u_z = mu_z + std_z * eps_z
        mu_h = self._helper_mean(obs, s_norm, u_z)
        eps_h = noise(mu_h)
        eps = torch.cat((eps_z, eps_h), dim=-1)
        log_prob = (-0.5 * eps.square() - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        return torch.cat((u_z, mu_h + std_h * eps_h), dim=-1), log_prob
