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

# How Eq. 1's squared errors are reduced over their dimensions (see `physicsvae_loss`).
PHYSICSVAE_REDUCTIONS = ("mean", "sum")


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
    beta: float | torch.Tensor,
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
    beta: float | torch.Tensor,
    reduction: str = "mean",
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """PhysicsVAE's Eq. 1: ‖a − a'‖² + α·‖s_{t+1} − s'_{t+1}‖² + β·KL(N(μ, σ) ‖ N(0, I)).

    actions, expert_actions: [N, T, A] the decoder's and the expert's actions.
    predicted_next, next_states: [N, T, D] features of W(s_t, a') and of the expert's s_{t+1}.
    kl: [N, T], summed over the latent. With α = 0 the simulation term drops out: plain behaviour cloning.
    reduction: how the squared errors are reduced over their dimensions before the mean over the batch.
      "mean": averaged over the A action and D state dimensions, as the authors' trainer does
              (`nn.MSELoss`); Table 1's α = 1e-4, β = 2 and Fig. 9's α axis were set with it.
      "sum":  summed over them, Eq. 1 as printed; then α weighs the state term D / A times more
              against the actions than the paper's α does, and β weighs the KL A times less.
    The KL is summed over the latent under both, as in the authors' code.
    """
    if reduction not in PHYSICSVAE_REDUCTIONS:
        raise ValueError(f"reduction must be one of {PHYSICSVAE_REDUCTIONS}, got {reduction!r}")
    reduce = (lambda e: e.mean(-1)) if reduction == "mean" else (lambda e: e.sum(-1))
    terms = {
        "bc": reduce((actions - expert_actions) ** 2).mean(),
        "sim": reduce((predicted_next - next_states) ** 2).mean(),
        "kl": kl.mean(),
    }
    return terms["bc"] + alpha * terms["sim"] + beta * terms["kl"], terms


def pulse_loss(
    actions: torch.Tensor,
    teacher_actions: torch.Tensor,
    latent_means: torch.Tensor,
    kl: torch.Tensor,
    lambda_regu: float,
    beta: float | torch.Tensor,
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
