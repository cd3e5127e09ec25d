"""Task terms, rewards and goal observations on hand-made body states, with hand-worked answers."""

from __future__ import annotations

import math

import pytest
import torch

from workers.losses.task import (
    DEFAULT_WEIGHTS,
    GOAL_DIMS,
    task_loss,
    task_reward,
    task_terms,
)
from workers.models.body_state import VR_POINTS, quat_mul, vr_points
from workers.models.task import goal_observation, goal_observation_dim

NUM_BODIES = 15
HEAD, LEFT_HAND, RIGHT_HAND = (body for _, body, _ in VR_POINTS)


def yaw_quat(theta: float) -> torch.Tensor:
    return torch.tensor([math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)])


def pose(yaw: float = 0.0, root=(0.0, 0.0, 0.9), vel=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """Body states [1, 15, 13]: every body turned by `yaw` and at the root's position `root`, except the
    neck body 0.4 m above it and the wrists 0.1 m above it and 0.3 m to either side (along y); the
    root moving at `vel`."""
    bs = torch.zeros(1, NUM_BODIES, 13)
    bs[..., 3:7] = yaw_quat(yaw)
    bs[0, :, :3] = torch.tensor(root)
    bs[0, HEAD, :3] += torch.tensor([0.0, 0.0, 0.4])
    bs[0, LEFT_HAND, :3] += torch.tensor([0.0, 0.3, 0.1])
    bs[0, RIGHT_HAND, :3] += torch.tensor([0.0, -0.3, 0.1])
    bs[0, 0, 7:10] = torch.tensor(vel)
    return bs


def test_vr_points_match_the_humanoid(character):
    c = character
    names = {term: c.body_names[body] for term, body, _ in VR_POINTS}
    assert names == {"head": "neck", "left_hand": "left_wrist", "right_hand": "right_wrist"}
    # The head is the neck body's sphere; the hands the wrist spheres, at their bodies' origins.
    for term, body, offset in VR_POINTS:
        geom = c.model.body_geomadr[body + 1]  # Character's bodies skip the world
        assert c.model.geom_bodyid[geom] == body + 1
        assert c.model.geom_pos[geom].tolist() == pytest.approx(list(offset)), term


def test_heading_error_zero_facing_the_goal_and_pi_facing_away():
    goal = torch.tensor([[0.7, 0.0]])
    torch.testing.assert_close(task_terms("heading", pose(0.7), goal)["heading"], torch.tensor([0.0]))
    away = task_terms("heading", pose(0.7 + math.pi), goal)["heading"]
    torch.testing.assert_close(away, torch.tensor([math.pi]), atol=1e-5, rtol=0)


def test_speed_error_counts_the_velocity_along_the_goal_direction():
    # θ* = π/2 (along +y), v* = 2: a root moving (0.5, 2, 0) has 2 m/s along y: no error, whatever
    # its sideways velocity; moving (0, 1, 0) misses by 1 m/s, normalised by max(2, 1): 0.5.
    goal = torch.tensor([[math.pi / 2, 2.0]])
    along = task_terms("heading", pose(math.pi / 2, vel=(0.5, 2.0, 0.0)), goal)["speed"]
    torch.testing.assert_close(along, torch.tensor([0.0]), atol=1e-6, rtol=0)
    slow = task_terms("heading", pose(math.pi / 2, vel=(0.0, 1.0, 0.0)), goal)["speed"]
    torch.testing.assert_close(slow, torch.tensor([0.5]))


def test_steering_direction_error_comes_from_the_velocity():
    # Facing +x (θ_h* = 0 met) but moving along (1, 1): travel direction π/4, θ_v* = 0 misses by π/4;
    # planar speed √2 against v* = √2: no speed error.
    goal = torch.tensor([[0.0, 0.0, math.sqrt(2.0)]])
    terms = task_terms("steering", pose(0.0, vel=(1.0, 1.0, 0.3)), goal)
    torch.testing.assert_close(terms["heading"], torch.tensor([0.0]))
    torch.testing.assert_close(terms["direction"], torch.tensor([math.pi / 4]))
    torch.testing.assert_close(terms["speed"], torch.tensor([0.0]), atol=1e-5, rtol=0)


def test_point_goal_distance_is_horizontal():
    # Root at (1, 2, 0.9), target (4, 6): 3-4-5; the root's height does not count.
    terms = task_terms("point_goal", pose(root=(1.0, 2.0, 0.9)), torch.tensor([[4.0, 6.0]]))
    torch.testing.assert_close(terms["distance"], torch.tensor([5.0]))


def test_height_sign_convention():
    # H = +1: a high root is a low loss (−h); H = −1: the loss is the height itself.
    high, low = pose(root=(0.0, 0.0, 0.9)), pose(root=(0.0, 0.0, 0.3))
    up, down = torch.tensor([[1.0]]), torch.tensor([[-1.0]])
    torch.testing.assert_close(task_terms("height", high, up)["height"], torch.tensor([-0.9]))
    torch.testing.assert_close(task_terms("height", high, down)["height"], torch.tensor([0.9]))
    assert task_terms("height", high, up)["height"] < task_terms("height", low, up)["height"]
    assert task_terms("height", low, down)["height"] < task_terms("height", high, down)["height"]


def test_vr_head_point_turns_with_the_neck():
    # The neck body at (0, 0, 1.3): upright, the head point is 0.175 m above it; the neck rolled 90°
    # about x carries it to (0, −0.175, 1.3).
    bs = pose()
    torch.testing.assert_close(vr_points(bs)[0, 0], torch.tensor([0.0, 0.0, 1.475]))
    bs[0, HEAD, 3:7] = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    torch.testing.assert_close(vr_points(bs)[0, 0], torch.tensor([0.0, -0.175, 1.3]))
    # Order: head, left hand (+y), right hand (−y).
    torch.testing.assert_close(vr_points(bs)[0, 1:], torch.tensor([[0.0, 0.3, 1.0], [0.0, -0.3, 1.0]]))


def test_vr_distances_zero_at_the_targets_and_one_metre_for_a_moved_hand():
    bs = pose(0.4, root=(2.0, -1.0, 0.9))
    goal = vr_points(bs).reshape(1, 9)
    terms = task_terms("vr", bs, goal)
    assert set(terms) == {"head", "left_hand", "right_hand"}
    for v in terms.values():
        torch.testing.assert_close(v, torch.tensor([0.0]), atol=1e-3, rtol=0)  # √1e−8 smoothing
    moved = bs.clone()
    moved[0, LEFT_HAND, :3] += torch.tensor([0.6, 0.0, -0.8])  # 1 m away (0.6² + 0.8² = 1)
    terms = task_terms("vr", moved, goal)
    torch.testing.assert_close(terms["left_hand"], torch.tensor([1.0]))
    torch.testing.assert_close(terms["head"] + terms["right_hand"], torch.tensor([0.0]), atol=1e-3, rtol=0)


def test_task_reward_is_exp_of_minus_the_weighted_terms_without_falls():
    # Facing and moving exactly as asked: L_g = 0 and the reward is 1, even with the root on the
    # floor (the fall term, 0.5 − 0.1 here, is not part of the reward).
    lying = pose(0.3, root=(0.0, 0.0, 0.1), vel=(math.cos(0.3), math.sin(0.3), 0.0))
    goal = torch.tensor([[0.3, 1.0]])
    torch.testing.assert_close(task_reward("heading", lying, goal, DEFAULT_WEIGHTS), torch.tensor([1.0]))
    total, _ = task_loss("heading", lying, goal, DEFAULT_WEIGHTS, fall_height=0.5)
    torch.testing.assert_close(total, torch.tensor([0.4]))
    # Point goal 5 m away with weight 0.5: e^(−2.5).
    reward = task_reward("point_goal", pose(root=(1.0, 2.0, 0.9)), torch.tensor([[4.0, 6.0]]), {"distance": 0.5})
    torch.testing.assert_close(reward, torch.tensor([math.exp(-2.5)]))


def test_unknown_task_is_rejected():
    with pytest.raises(ValueError, match="unknown task 'location'"):
        task_terms("location", pose(), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="unknown task"):
        goal_observation("dance", pose(), torch.zeros(1, 2))


@pytest.mark.parametrize("task", sorted(GOAL_DIMS))
def test_every_term_has_a_default_weight_and_the_dims_agree(task):
    goal = torch.ones(1, GOAL_DIMS[task])
    assert set(task_terms(task, pose(), goal)) <= DEFAULT_WEIGHTS.keys()
    assert goal_observation(task, pose(), goal).shape == (1, goal_observation_dim(task))


def move_scene(bs: torch.Tensor, goal: torch.Tensor, task: str, turn: float, shift: tuple[float, float]):
    """The character and its goal rotated by `turn` about the vertical through the origin, then moved
    horizontally by `shift`."""
    c, s = math.cos(turn), math.sin(turn)
    r = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = torch.tensor([shift[0], shift[1], 0.0])
    out = bs.clone()
    out[..., 0:3] = bs[..., 0:3] @ r.T + t
    out[..., 3:7] = quat_mul(yaw_quat(turn).expand_as(bs[..., 3:7]), bs[..., 3:7])
    out[..., 7:10], out[..., 10:13] = bs[..., 7:10] @ r.T, bs[..., 10:13] @ r.T
    g = goal.clone()
    if task in ("heading", "steering"):
        g[:, 0] += turn
    if task == "steering":
        g[:, 1] += turn
    if task == "point_goal":
        g[:, :2] = goal[:, :2] @ r[:2, :2].T + t[:2]
    if task == "vr":
        g = (goal.reshape(-1, 3, 3) @ r.T + t).reshape(-1, 9)
    return out, g


@pytest.mark.parametrize("task", sorted(GOAL_DIMS))
def test_goal_observation_is_invariant_to_turning_and_moving_the_scene(task):
    torch.manual_seed(0)
    bs = pose(0.3, root=(1.0, 2.0, 0.85), vel=(0.5, 0.2, 0.1))
    q = torch.randn(NUM_BODIES, 4)
    bs[0, 1:, 3:7] = q[1:] / q[1:].norm(dim=-1, keepdim=True)  # the neck tilted: the head point is off its body
    goals = {
        "heading": [0.8, 1.0],
        "steering": [0.8, -0.4, 1.0],
        "point_goal": [3.0, -1.0],
        "height": [1.0],
        "vr": [1.2, 2.3, 1.4, 1.0, 2.5, 1.1, 0.9, 1.6, 0.8],
    }
    goal = torch.tensor([goals[task]])
    moved_bs, moved_goal = move_scene(bs, goal, task, turn=1.1, shift=(-3.0, 0.5))
    torch.testing.assert_close(goal_observation(task, bs, goal), goal_observation(task, moved_bs, moved_goal))


def test_vr_goal_observation_known_answer():
    # Facing +y (yaw π/2) with the root at (1, 1, 0.9): a head target 1 m ahead of the root and 0.5 m
    # up is (1, 0, 0.5) in the heading frame; the body's head point is at (1, 1, 1.475), so the
    # error to close is (0, 0, 1.4 − 1.475) → ahead 1, up −0.075.
    bs = pose(math.pi / 2, root=(1.0, 1.0, 0.9))
    goal = vr_points(bs).reshape(1, 9).clone()
    goal[0, :3] = torch.tensor([1.0, 2.0, 1.4])
    obs = goal_observation("vr", bs, goal)
    torch.testing.assert_close(obs[0, :3], torch.tensor([1.0, 0.0, 0.5]))
    torch.testing.assert_close(obs[0, 9:12], torch.tensor([1.0, 0.0, -0.075]))
    torch.testing.assert_close(obs[0, 12:], torch.zeros(6))  # the hands are on target
