"""The world model's loss: error of a T-step synthetic rollout against the recorded one (ControlVAE Eq. 14/17)."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from workers.models.body_state import ANG, LIN, POS, QUAT, quat_to_matrix

WORLD_MODEL_TERMS = ("pos", "rot", "lin_vel", "ang_vel")


def world_model_loss(
    predicted: torch.Tensor, recorded: torch.Tensor, weights: Mapping[str, float]
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Weighted error of predicted body states against recorded ones, in world coordinates.

    predicted, recorded: [N, T, B, 13] body states (`workers.models.body_state`).
    weights: W' of Eq. 17, one per term in WORLD_MODEL_TERMS.

    Each term is the mean absolute error over N, T, bodies and coordinates (an L1
    distance, as SuperTrack and ControlVAE's code use, in place of Eq. 17's square):
    pos (m), rot (entries of the rotation matrix, free of the quaternion's sign),
    lin_vel (m/s), ang_vel (rad/s). Returns (Σ w_k · term_k, {k: term_k}).
    """
    terms = {
        "pos": (predicted[..., POS] - recorded[..., POS]).abs().mean(),
        "rot": (quat_to_matrix(predicted[..., QUAT]) - quat_to_matrix(recorded[..., QUAT])).abs().mean(),
        "lin_vel": (predicted[..., LIN] - recorded[..., LIN]).abs().mean(),
        "ang_vel": (predicted[..., ANG] - recorded[..., ANG]).abs().mean(),
    }
    total = sum(weights[k] * v for k, v in terms.items())
    return total, terms


def regression_loss(predicted: torch.Tensor, recorded: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """PhysicsVAE's simulation layer loss: the mean squared error of predicted next-state features [..., D]
    against the recorded ones, averaged over every element (the authors' nn.MSELoss)."""
    mse = ((predicted - recorded) ** 2).mean()
    return mse, {"mse": mse}
