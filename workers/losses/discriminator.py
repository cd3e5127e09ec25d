"""Adversarial motion prior losses (Peng et al. 2021, AMP, Eq. 6-8), as pure functions.

Shapes: B transitions, D input features. Every function returns
(total, {name: term}); the learner turns the terms into floats.

Loss types:
  lsgan - least squares with targets +1 for data and -1 for policy samples (AMP Eq. 6),
          style reward max(0, 1 - 0.25 (D - 1)²) (Eq. 7).
  bce   - sigmoid cross-entropy with labels 1 for data and 0 for policy samples
          (GAIL's objective), style reward -log(1 - sigmoid(D)).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

LOSS_TYPES = ("lsgan", "bce")

# 1 - sigmoid(D) is clamped to at least this before the log of the bce reward: r ≤ -log(1e-4) ≈ 9.2.
BCE_REWARD_EPS = 1e-4


def check_loss_type(loss: str) -> None:
    if loss not in LOSS_TYPES:
        raise ValueError(f"unknown discriminator loss type {loss!r}; expected one of {LOSS_TYPES}")


def discriminator_loss(
    d_data: torch.Tensor, d_policy: torch.Tensor, loss: str = "lsgan"
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The classification part of the discriminator objective.

    d_data:   [B] logits on data (reference) transitions.
    d_policy: [B'] logits on policy transitions (B' may differ from B).
    loss:     "lsgan" or "bce".

    lsgan: E_data (D - 1)² + E_policy (D + 1)², the sum as in AMP Eq. 6 and 8
           (no ½ in front), so that w_gp keeps its paper meaning relative to it.
    bce:   E_data[-log σ(D)] + E_policy[-log(1 - σ(D))], summed the same way.

    Returns (total [], {"loss_data": [], "loss_policy": []}).
    """
    check_loss_type(loss)
    if loss == "lsgan":
        data = (d_data - 1.0).pow(2).mean()
        policy = (d_policy + 1.0).pow(2).mean()
    else:
        data = F.binary_cross_entropy_with_logits(d_data, torch.ones_like(d_data))
        policy = F.binary_cross_entropy_with_logits(d_policy, torch.zeros_like(d_policy))
    return data + policy, {"loss_data": data, "loss_policy": policy}


def gradient_penalty(
    outputs: torch.Tensor, inputs: torch.Tensor, w_gp: float
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """(w_gp / 2) · E ‖∇_φ D(φ)‖² (AMP Eq. 8), differentiable (create_graph=True).

    outputs: [B] discriminator outputs D(φ_i), each depending only on its own row of inputs.
    inputs:  [B, D] the features φ the outputs were computed from; must require grad.
    w_gp:    the penalty weight (AMP: 10; ControlVAE Eq. 27 writes w_g without the ½).

    Returns (penalty [], {"gp": [], "input_grad_norm": [] mean ‖∇_φ D‖, not differentiated}).
    """
    if not inputs.requires_grad:
        raise ValueError("gradient_penalty needs inputs that require grad and the outputs computed from them")
    (grad,) = torch.autograd.grad(outputs.sum(), inputs, create_graph=True)
    penalty = 0.5 * w_gp * grad.pow(2).sum(-1).mean()
    return penalty, {"gp": penalty, "input_grad_norm": grad.detach().norm(dim=-1).mean()}


def logit_regularization(weight: torch.Tensor, w: float) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """w · ‖W‖² on the logit layer's weights W [1, H] (keeps logits from growing without bound).

    Returns (penalty [], {"logit_reg": []}).
    """
    penalty = w * weight.pow(2).sum()
    return penalty, {"logit_reg": penalty}


def style_reward(d: torch.Tensor, loss: str = "lsgan") -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The policy's style reward from discriminator logits; no gradient flows back.

    d: [B] logits on policy transitions.
    lsgan: max(0, 1 - 0.25 (D - 1)²) ∈ [0, 1] (AMP Eq. 7): 1 at D = 1, 0 at D ≤ -1 or D ≥ 3.
    bce:   -log(max(1 - σ(D), 1e-4)) ∈ [0, 9.2], the GAIL form.

    Returns (reward [B], {"style_reward": [] mean, "logit": [] mean D}).
    """
    check_loss_type(loss)
    d = d.detach()
    if loss == "lsgan":
        r = (1.0 - 0.25 * (d - 1.0).pow(2)).clamp(min=0.0)
    else:
        r = -torch.log((1.0 - torch.sigmoid(d)).clamp(min=BCE_REWARD_EPS))
    return r, {"style_reward": r.mean(), "logit": d.mean()}
