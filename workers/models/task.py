"""The task policy on a frozen VAE controller.

z = μ_p(s) + μ_g(s, g): a residual on the prior mean (ControlVAE Eq. 21, PULSE
Eq. 4; with the standard normal prior μ_p = 0 and μ_g is PhysicsVAE's task
encoder; without `prior_action`, PULSE's ablation, z = μ_g). ControlVAE's task
policy is a Gaussian around that mean with the prior's standard deviation, sampled
with the reparameterisation trick (`eps`). The action is the frozen decoder's,
plus the helper branch Δa = σ · tanh(H(s, z)) when σ > 0 (PhysicsVAE Eq. 2), so
that no action dimension moves by more than σ from what the decoder would do.

`goal_observation` is what the policy sees of its goal: the goal in the character's heading frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from workers.models.body_state import POS, QUAT, vr_points, yaw, yaw_matrix
from workers.models.nets import Normalizer, mlp
from workers.models.vae import VAEController


class TaskPolicy(nn.Module):
    def __init__(
        self,
        state_dim: int,
        goal_dim: int,
        latent_dim: int,
        action_dim: int,
        hidden: Sequence[int] = (256, 128),
        helper_hidden: Sequence[int] = (128, 128),
        sigma: float = 0.0,
        act: str = "elu",
        prior_action: bool = True,
    ):
        super().__init__()
        if sigma < 0:
            raise ValueError(f"helper sigma must be non-negative, got {sigma}")
        self.sigma = sigma
        self.prior_action = prior_action
        self.state_norm = Normalizer(state_dim)
        self.encoder = mlp(state_dim + goal_dim, hidden, latent_dim, act, out_scale=0.1)
        self.helper = mlp(state_dim + latent_dim, helper_hidden, action_dim, act, out_scale=0.1) if sigma > 0 else None

    def latent_offset(self, s: torch.Tensor, goal_obs: torch.Tensor) -> torch.Tensor:
        """μ_g(s, g) [..., Z]."""
        return self.encoder(torch.cat((self.state_norm(s), goal_obs), dim=-1))

    def helper_offset(self, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Δa = σ · tanh(H(s, z)) [..., A]; zero without a helper branch."""
        if self.helper is None:
            return s.new_zeros(())
        return self.sigma * torch.tanh(self.helper(torch.cat((self.state_norm(s), z), dim=-1)))

    def latent(
        self, controller: VAEController, s: torch.Tensor, goal_obs: torch.Tensor, eps: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(z [..., Z], μ_g [..., Z]): the prior's mean plus μ_g, plus the prior's std times `eps` if given."""
        mu_g = self.latent_offset(s, goal_obs)
        if not self.prior_action and eps is None:
            return mu_g, mu_g
        prior = controller.prior_dist(s)
        z = prior.mean + mu_g if self.prior_action else mu_g
        if eps is not None:
            z = z + prior.log_std.exp() * eps
        return z, mu_g

    def forward(
        self, controller: VAEController, s: torch.Tensor, goal_obs: torch.Tensor, eps: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(action [..., A], μ_g [..., Z]) for features s [..., D] and goal observations [..., G]."""
        action, _, mu_g = self.act(controller, s, goal_obs, eps)
        return action, mu_g

    def act(
        self, controller: VAEController, s: torch.Tensor, goal_obs: torch.Tensor, eps: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(applied action, the decoder's own action D(s, z), μ_g): the two actions differ by the helper's Δa."""
        z, mu_g = self.latent(controller, s, goal_obs, eps)
        decoded = controller.act(s, z)
        if self.helper is None:
            return decoded, decoded, mu_g
        return decoded + self.helper_offset(s, z), decoded, mu_g


GOAL_OBSERVATION_DIMS = {"heading": 3, "height": 1, "steering": 5, "point_goal": 3, "vr": 18}


def _to_heading_frame(heading: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """World vectors v [N, K, 3] in the heading frame of yaw angles heading [N]."""
    return (yaw_matrix(-heading).unsqueeze(-3) @ v.unsqueeze(-1)).squeeze(-1)


def goal_observation(task: str, bs: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """What the task policy sees of the goal [N, G_obs], in the character's heading frame (rotation
    about the vertical and horizontal translation of the whole scene leave it unchanged):

      heading     cos, sin of θ* − θ_h; v*                                          (3)
      height      H                                                                (1)
      steering    cos, sin of θ_h* − θ_h and of θ_v* − θ_h; v*                     (5)
      point_goal  the target relative to the root (x, y) and its distance           (3)
      vr          each target relative to the root (9), then each target relative to its tracked
                  point (9): the error to close, which the policy would otherwise have to work out
                  from the neck's rotation (the head point is offset from its body) (18)
    """
    if task not in GOAL_OBSERVATION_DIMS:
        raise ValueError(f"unknown task {task!r}; expected one of {sorted(GOAL_OBSERVATION_DIMS)}")
    heading = yaw(bs[..., 0, QUAT])
    if task == "heading":
        d = goal[..., 0] - heading
        return torch.stack((torch.cos(d), torch.sin(d), goal[..., 1]), dim=-1)
    if task == "height":
        return goal[..., :1]
    if task == "steering":
        dh, dv = goal[..., 0] - heading, goal[..., 1] - heading
        return torch.stack((torch.cos(dh), torch.sin(dh), torch.cos(dv), torch.sin(dv), goal[..., 2]), dim=-1)
    if task == "point_goal":
        rel = torch.zeros(goal.shape[:-1] + (3,), dtype=goal.dtype, device=goal.device)
        rel[..., :2] = goal[..., :2] - bs[..., 0, POS][..., :2]
        local = _to_heading_frame(heading, rel.unsqueeze(-2))[..., 0, :2]
        return torch.cat((local, local.norm(dim=-1, keepdim=True)), dim=-1)
    targets = goal.unflatten(-1, (3, 3))  # vr
    root = _to_heading_frame(heading, targets - bs[..., :1, POS])
    error = _to_heading_frame(heading, targets - vr_points(bs))
    return torch.cat((root.flatten(-2), error.flatten(-2)), dim=-1)


def goal_observation_dim(task: str) -> int:
    return GOAL_OBSERVATION_DIMS[task]
