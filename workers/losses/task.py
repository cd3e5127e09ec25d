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

from workers.models.body_state import LIN, POS, QUAT, quat_to_matrix, yaw, yaw_matrix

GOAL_DIMS = {"heading": 2, "height": 1, "steering": 3, "point_goal": 2, "vr": 9}

# The points a VR rig tracks, as (term, body index, offset in the body's frame) on our humanoid
# (workers/body/assets/humanoid.xml, bodies in file order without the world). The humanoid has no head
# body: the neck body (2) carries the head, a sphere of radius 0.1025 m centred 0.175 m above the neck
# joint, so the headset is that sphere's centre, where the neck body's origin (the joint, at the base
# of the neck) would not move with the head at all. The hands are the wrist bodies (right 5, left 8),
# whose hand spheres sit at their origins. tests/unit/test_task_losses.py checks these against the model.
VR_POINTS = (
    ("head", 2, (0.0, 0.0, 0.175)),
    ("left_hand", 8, (0.0, 0.0, 0.0)),
    ("right_hand", 5, (0.0, 0.0, 0.0)),
)
VR_TERMS = tuple(name for name, _, _ in VR_POINTS)


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


def vr_points(bs: torch.Tensor) -> torch.Tensor:
    """World positions [..., 3, 3] of the tracked points (head, left hand, right hand) of body states [..., B, 13]."""
    index = [body for _, body, _ in VR_POINTS]
    offset = torch.tensor([o for _, _, o in VR_POINTS], dtype=bs.dtype, device=bs.device)  # [3, 3]
    pos, quat = bs[..., index, POS], bs[..., index, QUAT]
    return pos + (quat_to_matrix(quat) @ offset.unsqueeze(-1)).squeeze(-1)


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


def _to_heading_frame(heading: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """World vectors v [N, K, 3] in the heading frame of yaw angles heading [N]."""
    return (yaw_matrix(-heading).unsqueeze(-3) @ v.unsqueeze(-1)).squeeze(-1)


def goal_observation(task: str, bs: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """What the task policy sees of the goal [N, G_obs], in the character's heading frame (rotation
    about the vertical and horizontal translation of the whole scene leave it unchanged):

      heading     cos, sin of θ* − θ_h; v*                                          (3)
      height      H                                                                (1)
      steering    cos, sin of θ_h* − θ_h and of θ_v* − θ_h; v*                     (5)
      point_goal  the target relative to the root (x, y) and its distance           (3)
      vr          each target relative to the root (9), then each target relative to its tracked
                  point (9): the error to close, which the policy would otherwise have to work out
                  from the neck's rotation (the head point is offset from its body) (18)
    """
    if task not in TASK_TERMS:
        raise ValueError(f"unknown task {task!r}; expected one of {sorted(TASK_TERMS)}")
    heading = yaw(bs[..., 0, QUAT])
    if task == "heading":
        d = goal[..., 0] - heading
        return torch.stack((torch.cos(d), torch.sin(d), goal[..., 1]), dim=-1)
    if task == "height":
        return goal[..., :1]
    if task == "steering":
        dh, dv = goal[..., 0] - heading, goal[..., 1] - heading
        return torch.stack((torch.cos(dh), torch.sin(dh), torch.cos(dv), torch.sin(dv), goal[..., 2]), dim=-1)
    if task == "point_goal":
        rel = torch.zeros(goal.shape[:-1] + (3,), dtype=goal.dtype, device=goal.device)
        rel[..., :2] = goal[..., :2] - bs[..., 0, POS][..., :2]
        local = _to_heading_frame(heading, rel.unsqueeze(-2))[..., 0, :2]
        return torch.cat((local, local.norm(dim=-1, keepdim=True)), dim=-1)
    targets = goal.unflatten(-1, (3, 3))  # vr
    root = _to_heading_frame(heading, targets - bs[..., :1, POS])
    error = _to_heading_frame(heading, targets - vr_points(bs))
    return torch.cat((root.flatten(-2), error.flatten(-2)), dim=-1)


GOAL_OBSERVATION_DIMS = {"heading": 3, "height": 1, "steering": 5, "point_goal": 3, "vr": 18}


def goal_observation_dim(task: str) -> int:
    return GOAL_OBSERVATION_DIMS[task]
