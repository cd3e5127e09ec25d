"""AMP's discriminator D(Φ(s), Φ(s')): a transition of observation features in, one logit out.

Peng et al. 2021, Sec. 5.2-5.4 and 6.2: an MLP (1024, 512) ReLU with a linear
output. ControlVAE's skill discriminator (Eq. 27) is the same network
conditioned on a skill label c; `num_skills > 0` turns that on.

Input scaling: one `Normalizer` over Φ, shared by both states of the
transition, updated by the learner from data (reference) samples only, so the
policy cannot move the scale it is judged on.

Gradient penalty convention: the penalty is taken with respect to the
*normalised* features φ̃ = (Φ - mean) / std, i.e. on the input of `logits`
(as AMP's public code does). Since the normaliser is a fixed per-feature
affine map during a step, ∇_Φ D = ∇_φ̃ D / std; the choice only rescales each
feature's share of the penalty, and on normalised inputs every feature has
unit scale.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

from workers.models.nets import Normalizer, mlp


class Discriminator(nn.Module):
    """D(φ, c) -> logit.

    obs_dim:   size of Φ(s) for one state; the input is the pair, [B, 2·obs_dim].
    hidden:    hidden layer sizes (AMP: 1024, 512).
    act:       hidden activation (AMP: ReLU).
    num_skills: number of skill classes the discriminator is conditioned on; 0 for none.
    skill_embed_dim: 0 feeds the skill as a one-hot vector; > 0 through a learned embedding of that size.
    """

    def __init__(
        self,
        obs_dim: int,
        hidden: Sequence[int] = (1024, 512),
        act: str = "relu",
        num_skills: int = 0,
        skill_embed_dim: int = 0,
    ):
        super().__init__()
        if obs_dim < 1 or num_skills < 0 or skill_embed_dim < 0:
            raise ValueError(f"bad discriminator sizes: obs_dim={obs_dim}, num_skills={num_skills}")
        self.obs_dim = obs_dim
        self.num_skills = num_skills
        self.normalizer = Normalizer(obs_dim)
        self.skill_embed = nn.Embedding(num_skills, skill_embed_dim) if num_skills and skill_embed_dim else None
        skill_dim = (skill_embed_dim or num_skills) if num_skills else 0
        self.net = mlp(2 * obs_dim + skill_dim, hidden, 1, act)

    @property
    def in_dim(self) -> int:
        """Size of the transition input, 2·obs_dim."""
        return 2 * self.obs_dim

    @property
    def logit_layer(self) -> nn.Linear:
        """The last linear layer (for logit regularisation)."""
        return self.net[-1]

    @torch.no_grad()
    def update_normalizer(self, obs: torch.Tensor) -> None:
        """Accumulate Φ statistics from transitions [B, 2·obs_dim] (both states count)."""
        self.normalizer.update(obs.reshape(-1, self.obs_dim))

    def normalize(self, obs: torch.Tensor) -> torch.Tensor:
        """[B, 2·obs_dim] raw transitions -> [B, 2·obs_dim] normalised ones."""
        self._check_obs(obs)
        return self.normalizer(obs.reshape(-1, 2, self.obs_dim)).reshape(obs.shape)

    def logits(self, obs_n: torch.Tensor, skill: torch.Tensor | None = None) -> torch.Tensor:
        """D on already-normalised transitions [B, 2·obs_dim] -> logits [B].

        This is the function the gradient penalty differentiates: make `obs_n`
        require grad and pass the output and `obs_n` to `gradient_penalty`.
        """
        self._check_obs(obs_n)
        if self.num_skills == 0 and skill is not None:
            raise ValueError("this discriminator is not skill-conditioned (num_skills=0) but got skill labels")
        x = obs_n if self.num_skills == 0 else torch.cat((obs_n, self._skill_code(skill, obs_n)), dim=-1)
        return self.net(x).squeeze(-1)

    def forward(self, obs: torch.Tensor, skill: torch.Tensor | None = None) -> torch.Tensor:
        """D on raw transitions [B, 2·obs_dim] (and skills [B] int) -> logits [B]."""
        return self.logits(self.normalize(obs), skill)

    def _skill_code(self, skill: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
        if skill is None:
            raise ValueError(f"this discriminator is conditioned on {self.num_skills} skills; pass skill labels")
        skill = skill.long()
        if skill.shape != like.shape[:1]:
            raise ValueError(f"skill labels have shape {tuple(skill.shape)}, expected {tuple(like.shape[:1])}")
        if self.skill_embed is not None:
            return self.skill_embed(skill).to(like.dtype)
        return F.one_hot(skill, self.num_skills).to(like.dtype)

    def _check_obs(self, obs: torch.Tensor) -> None:
        if obs.ndim != 2 or obs.shape[-1] != self.in_dim:
            raise ValueError(f"discriminator input has shape {tuple(obs.shape)}, expected [B, {self.in_dim}]")
