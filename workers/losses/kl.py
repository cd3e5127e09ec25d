"""The KL divergence between diagonal Gaussians, written once for every prior type."""

from __future__ import annotations

import torch


def gaussian_kl(
    mean_q: torch.Tensor, log_std_q: torch.Tensor, mean_p: torch.Tensor, log_std_p: torch.Tensor
) -> torch.Tensor:
    """KL(N(μ_q, σ_q²) ‖ N(μ_p, σ_p²)) [...] summed over the last (latent) dimension of [..., Z] inputs.

    Per dimension: log(σ_p/σ_q) + (σ_q² + (μ_q − μ_p)²) / (2σ_p²) − ½.
    With σ_q = σ_p and μ_q = μ_p + r this is ‖r‖² / (2σ_p²), ControlVAE's KL term
    (Eq. 11; Eq. 9 as printed has a typo);
    with μ_p = 0, σ_p = 1 it is the usual VAE term.
    """
    return gaussian_kl_per_dim(mean_q, log_std_q, mean_p, log_std_p).sum(-1)


def gaussian_kl_per_dim(
    mean_q: torch.Tensor, log_std_q: torch.Tensor, mean_p: torch.Tensor, log_std_p: torch.Tensor
) -> torch.Tensor:
    """`gaussian_kl`'s terms [..., Z], one per latent dimension, before the sum."""
    var_ratio = torch.exp(2 * (log_std_q - log_std_p))
    mahalanobis = ((mean_q - mean_p) * torch.exp(-log_std_p)) ** 2
    return log_std_p - log_std_q + 0.5 * (var_ratio + mahalanobis) - 0.5


def latent_usage(mean_q: torch.Tensor, log_std_q: torch.Tensor, active: float = 0.01) -> dict[str, torch.Tensor]:
    """How a posterior N(μ_q, σ_q²) over a batch [N, Z] uses its latent against N(0, I):

    - `kl_per_dim` [Z]: the KL of each dimension, averaged over the batch (nats); a collapsed dimension's is ~0;
    - `kl`: their sum, the KL term's value;
    - `active_dims`: the dimensions whose posterior mean varies over the batch, Var_x(μ_q) > `active`
      (Burda et al. 2016's active units): a dimension the encoder does not use has μ_q ≈ 0 for every input.
    """
    kl = gaussian_kl_per_dim(mean_q, log_std_q, torch.zeros_like(mean_q), torch.zeros_like(log_std_q)).mean(0)
    return {"kl_per_dim": kl, "kl": kl.sum(), "active_dims": (mean_q.var(0) > active).sum()}
