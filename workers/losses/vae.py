"""The VAE controller's three objectives, as pure functions of tensors.

controlvae  reconstruction through world-model rollouts + β·KL + action regularisation
            (ControlVAE Eq. 10–13, 16);
physicsvae  behaviour cloning + α·simulation consistency + β·KL (PhysicsVAE Eq. 1);
pulse       distillation + λ·L_regu + β·KL to the learned prior (PULSE Eq. 3).

Sums over time are discounted by γ^t where the paper does, and every objective is
averaged over the batch; sequences are normalised by Σ_t γ^t so that a term's size
does not depend on the rollout length.
"""

from __future__ import annotations

import torch


def discounts(steps: int, gamma: float, like: torch.Tensor) -> torch.Tensor:
    """γ^t for t < steps, normalised to sum to one, [T]."""
    w = gamma ** torch.arange(steps, dtype=like.dtype, device=like.device)
    return w / w.sum()


def controlvae_loss(
    predicted: torch.Tensor,
    reference: torch.Tensor,
    kl: torch.Tensor,
    actions: torch.Tensor,
    state_weights: torch.Tensor,
    gamma: float,
    beta: float,
    w_a1: float,
    w_a2: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """ControlVAE's loss over synthetic rollouts (Eq. 13 with Eq. 16 for L_rec).

    predicted, reference: features s [N, T, D] of the rollout and of the reference clip.
    kl: [N, T] KL(q ‖ p) per step. actions: [N, T, A] the policy's actions.
    state_weights: W of Eq. 16 as a per-feature weight [D].
    Returns (L_rec + β·L_kl + L_act, {"rec", "kl", "act"}).
    """
    w = discounts(predicted.shape[1], gamma, predicted)
    rec = ((reference - predicted).abs() * state_weights).sum(-1)  # [N, T]
    act = w_a1 * actions.abs().sum(-1) + w_a2 * (actions**2).sum(-1)
    terms = {"rec": (rec * w).sum(-1).mean(), "kl": (kl * w).sum(-1).mean(), "act": (act * w).sum(-1).mean()}
    return terms["rec"] + beta * terms["kl"] + terms["act"], terms


def physicsvae_loss(
    actions: torch.Tensor,
    expert_actions: torch.Tensor,
    predicted_next: torch.Tensor,
    next_states: torch.Tensor,
    kl: torch.Tensor,
    alpha: float,
    beta: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """PhysicsVAE's Eq. 1: Σ‖a − a'‖² + α·‖s_{t+1} − s'_{t+1}‖² + β·KL(N(μ, σ) ‖ N(0, I)).

    actions, expert_actions: [N, T, A] the decoder's and the expert's actions.
    predicted_next, next_states: [N, T, D] features of W(s_t, a') and of the expert's s_{t+1}.
    kl: [N, T]. With α = 0 the simulation term drops out: plain behaviour cloning.
    """
    terms = {
        "bc": ((actions - expert_actions) ** 2).sum(-1).mean(),
        "sim": ((predicted_next - next_states) ** 2).sum(-1).mean(),
        "kl": kl.mean(),
    }
    return terms["bc"] + alpha * terms["sim"] + beta * terms["kl"], terms


def pulse_loss(
    actions: torch.Tensor,
    teacher_actions: torch.Tensor,
    latent_means: torch.Tensor,
    kl: torch.Tensor,
    lambda_regu: float,
    beta: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """PULSE's Eq. 3: ‖a_teacher − a‖² + λ·L_regu + β·KL(E ‖ R).

    actions, teacher_actions: [N, T, A]. latent_means: [N, T, Z] the encoder's means
    μ_e over consecutive steps; L_regu = ‖μ_e,t − μ_e,t−1‖² over the T − 1 pairs.
    kl: [N, T] KL of the encoder to the learned prior.
    """
    if latent_means.shape[1] > 1:
        regu = ((latent_means[:, 1:] - latent_means[:, :-1]) ** 2).sum(-1).mean()
    else:
        regu = latent_means.new_zeros(())
    terms = {"distill": ((actions - teacher_actions) ** 2).sum(-1).mean(), "regu": regu, "kl": kl.mean()}
    return terms["distill"] + lambda_regu * terms["regu"] + beta * terms["kl"], terms
