"""Trained policies as plain `nn.Module`s from an observation to PD targets, for export (MLflow models).

Each takes a float32 batch [N, obs_dim] and returns the deterministic action [N, A]:
- `PriorMeanController`: a VAE controller (ControlVAE, PhysicsVAE, PULSE) acting with z = μ_p(s),
  the mean of its prior, on the body-state features s (`workers.models.body_state.features`);
- `ActorMean`: a PPO actor-critic's mean action μ(o). For residual policies (the tracker) this is
  the offset added to the reference's next pose, not the PD target itself.
"""

from __future__ import annotations

import torch
from torch import nn

from workers.models.actor_critic import ActorCritic
from workers.models.vae import VAEController


class PriorMeanController(nn.Module):
    def __init__(self, controller: VAEController):
        super().__init__()
        self.controller = controller

    def forward(self, s: torch.Tensor) -> torch.Tensor:
        return self.controller.act(s, self.controller.prior_dist(s).mean)


class ActorMean(nn.Module):
    def __init__(self, module: ActorCritic):
        super().__init__()
        self.module = module

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.module.mean(obs)
