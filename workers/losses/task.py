"""Downstream task losses (ControlVAE §4.3, Eq. 22–26), a point goal and VR tracking (PULSE §5), as pure functions.

Each task maps a body state [N, B, 13] (the state s_t after a step) and the goal
parameters [N, G] (world frame) to named terms [N]; `task_loss` adds the fall
penalty (Eq. 23) and weights the terms by name, `task_reward` is PPO's reward
e^(−L_g) without the fall term. Angles are in radians, lengths in metres.

Goal parameters by task:
  heading     (θ*, v*)          travel at speed v* along heading θ* (Eq. 25)
  height      (H,)              H = +1 keeps the root high, −1 low (Eq. 24)
  steering    (θ_h*, θ_v*, v*)  face θ_h* while moving along θ_v* at speed v* (Eq. 26)
  point_goal  (x*, y*)          bring the root to a point on the ground
  vr          (head xyz, left hand xyz, right hand xyz)
                                follow a headset and two hand controllers (PULSE's VR controller
                                tracking): the positions of `VR_POINTS` in a reference clip

`workers.task.goals` draws these goals for rollouts and judges success.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from workers.models.body_state import LIN, POS, QUAT, VR_TERMS, vr_points, yaw

GOAL_DIMS = {"heading": 2, "height": 1, "steering": 3, "point_goal": 2, "vr": 9}


def angle_difference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a − b| wrapped to [0, π]."""
    d = a - b
    return torch.atan2(torch.sin(d), torch.cos(d)).abs()


def _norm(v: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the last axis, smoothed (√(‖v‖² + 1e−8)) so that its gradient is finite at zero."""
    return torch.sqrt((v**2).sum(-1) + 1e-8)


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


def point_goal_terms(bs: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """Horizontal distance of the root to the target (metres)."""
    return {"distance": _norm(goal[..., :2] - bs[..., 0, POS][..., :2])}


def vr_terms(bs: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """Distance (metres) of each tracked point to its target: head, left_hand, right_hand."""
    d = _norm(vr_points(bs) - goal.unflatten(-1, (3, 3)))  # [N, 3]
    return {name: d[..., k] for k, name in enumerate(VR_TERMS)}


TASK_TERMS = {
    "heading": heading_terms,
    "height": height_terms,
    "steering": steering_terms,
    "point_goal": point_goal_terms,
    "vr": vr_terms,
}

# The paper's weights (Eq. 25–26: w_θh = 2, w_θv = 2, w_v = 1), fall penalty 1; the point goal's and
# the VR points' distances count one per metre.
DEFAULT_WEIGHTS = {
    "heading": 2.0,
    "direction": 2.0,
    "speed": 1.0,
    "height": 1.0,
    "distance": 1.0,
    **dict.fromkeys(VR_TERMS, 1.0),
    "fall": 1.0,
}


def task_terms(task: str, bs: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """The task's named terms {term: [N]} of body states [N, B, 13] and goals [N, G], without the fall term."""
    if task not in TASK_TERMS:
        raise ValueError(f"unknown task {task!r}; expected one of {sorted(TASK_TERMS)}")
    return TASK_TERMS[task](bs, goal)


def task_loss(
    task: str, bs: torch.Tensor, goal: torch.Tensor, weights: Mapping[str, float], fall_height: float
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """L_g(s_t) + L_fall(s_t) per sample: (total [N], {term: [N]}) for body states [N, B, 13] and goals [N, G]."""
    terms = task_terms(task, bs, goal)
    terms["fall"] = fall_penalty(bs, fall_height)
    total = sum(weights[k] * v for k, v in terms.items())
    return total, terms


def task_reward(task: str, bs: torch.Tensor, goal: torch.Tensor, weights: Mapping[str, float]) -> torch.Tensor:
    """exp(−L_g) [N]: PPO's reward, the weighted task terms without the fall term (ControlVAE compares
    learners on e^(−L_g)). It is 1 at zero loss; the height task's L_g = −H·h is negative when met,
    so its reward exceeds 1 there."""
    terms = task_terms(task, bs, goal)
    return torch.exp(-sum(weights[k] * v for k, v in terms.items()))
