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
    var_ratio = torch.exp(2 * (log_std_q - log_std_p))
    mahalanobis = ((mean_q - mean_p) * torch.exp(-log_std_p)) ** 2
    return (log_std_p - log_std_q + 0.5 * (var_ratio + mahalanobis) - 0.5).sum(-1)
