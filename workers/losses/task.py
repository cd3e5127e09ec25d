"""Downstream task losses (ControlVAE §4.3, Eq. 22–26) and a target-location loss, as pure functions.

Each task loss maps a step (s_{t−1}, s_t) of body states [N, B, 13] and the goal
parameters [N, G] (world frame) to named terms [N]; `task_loss` adds the fall
penalty (Eq. 23) and weights the terms by name. Angles are in radians.

Goal parameters by task:
  heading   (θ*, v*)         travel at speed v* along heading θ* (Eq. 25)
  height    (H,)             H = +1 keeps the root high, −1 low (Eq. 24)
  steering  (θ_h*, θ_v*, v*) face θ_h* while moving along θ_v* at speed v* (Eq. 26)
  location  (x*, y*)         reach a point on the ground
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from workers.models.body_state import LIN, POS, QUAT, yaw, yaw_matrix

GOAL_DIMS = {"heading": 2, "height": 1, "steering": 3, "location": 2}


def angle_difference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a − b| wrapped to [0, π]."""
    d = a - b
    return torch.atan2(torch.sin(d), torch.cos(d)).abs()


def fall_penalty(bs: torch.Tensor, threshold: float) -> torch.Tensor:
    """max(h* − h_root, 0) [N] (Eq. 23)."""
    return torch.relu(threshold - bs[..., 0, 2])


def heading_terms(bs: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """Eq. 25 terms: heading error |θ* − θ_h| and normalised speed error |v* − v| / max(v*, 1),
    with v the root velocity along the target direction."""
    theta, speed = goal[..., 0], goal[..., 1]
    v = bs[..., 0, LIN]
    along = v[..., 0] * torch.cos(theta) + v[..., 1] * torch.sin(theta)
    return {
        "heading": angle_difference(theta, yaw(bs[..., 0, QUAT])),
        "speed": (speed - along).abs() / speed.clamp(min=1.0),
    }


def height_terms(bs: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """Eq. 24 as a loss to minimise: −H · h_root (the paper's sign convention reads the other way
    round; this one makes H = +1 mean high, as its text describes)."""
    return {"height": -goal[..., 0] * bs[..., 0, 2]}


def steering_terms(bs: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """Eq. 26 terms: facing error, travel-direction error, planar speed error (normalised)."""
    v = bs[..., 0, LIN]
    planar = torch.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + 1e-8)
    return {
        "heading": angle_difference(goal[..., 0], yaw(bs[..., 0, QUAT])),
        "direction": angle_difference(goal[..., 1], torch.atan2(v[..., 1], v[..., 0])),
        "speed": (goal[..., 2] - planar).abs() / goal[..., 2].clamp(min=1.0),
    }


def location_terms(bs: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """Horizontal distance of the root to the target (metres)."""
    d = goal[..., :2] - bs[..., 0, POS][..., :2]
    return {"distance": torch.sqrt((d**2).sum(-1) + 1e-8)}


TASK_TERMS = {"heading": heading_terms, "height": height_terms, "steering": steering_terms, "location": location_terms}

# The paper's weights (Eq. 25–26: w_θh = 2, w_θv = 2, w_v = 1), fall penalty 1.
DEFAULT_WEIGHTS = {"heading": 2.0, "direction": 2.0, "speed": 1.0, "height": 1.0, "distance": 1.0, "fall": 1.0}


def task_loss(
    task: str, bs: torch.Tensor, goal: torch.Tensor, weights: Mapping[str, float], fall_height: float
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """L_g(s_t) + L_fall(s_t) per sample: (total [N], {term: [N]}) for body states [N, B, 13] and goals [N, G]."""
    terms = TASK_TERMS[task](bs, goal)
    terms["fall"] = fall_penalty(bs, fall_height)
    total = sum(weights[k] * v for k, v in terms.items())
    return total, terms


def goal_observation(task: str, bs: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """What the task policy sees of the goal, in the character's heading frame [N, G_obs]."""
    heading = yaw(bs[..., 0, QUAT])
    if task == "heading":
        d = goal[..., 0] - heading
        return torch.stack((torch.cos(d), torch.sin(d), goal[..., 1]), dim=-1)
    if task == "height":
        return goal[..., :1]
    if task == "steering":
        dh, dv = goal[..., 0] - heading, goal[..., 1] - heading
        return torch.stack((torch.cos(dh), torch.sin(dh), torch.cos(dv), torch.sin(dv), goal[..., 2]), dim=-1)
    if task == "location":
        rel = torch.zeros(goal.shape[:-1] + (3,), dtype=goal.dtype)
        rel[..., :2] = goal[..., :2] - bs[..., 0, POS][..., :2]
        local = (yaw_matrix(-heading) @ rel.unsqueeze(-1)).squeeze(-1)[..., :2]
        return torch.cat((local, local.norm(dim=-1, keepdim=True)), dim=-1)
    raise ValueError(f"unknown task {task!r}; expected one of {sorted(TASK_TERMS)}")


def goal_observation_dim(task: str) -> int:
    return {"heading": 3, "height": 1, "steering": 5, "location": 3}[task]
