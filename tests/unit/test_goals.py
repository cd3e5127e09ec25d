"""Goal sampling for rollouts and per-episode success, with hand-made body-state sequences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from workers.body import rotations as rot
from workers.models.body_state import VR_POINTS, pack
from workers.sim.env import BatchedSim
from workers.task.goals import (
    HEIGHT_HIGH_M,
    SUCCESS_RADIUS_M,
    GoalSampler,
    SuccessTracker,
)

NUM_BODIES = 15
HEAD, LEFT_HAND, RIGHT_HAND = (body for _, body, _ in VR_POINTS)
HZ = 10  # the tracker's rate in these tests: 1 s is 10 steps


def states(n: int, root=None, yaw=None, vel=None) -> np.ndarray:
    """Body states [n, 15, 13] with identity rotations (or every body turned by yaw [n]); roots [n, 3]."""
    bs = np.zeros((n, NUM_BODIES, 13), np.float32)
    bs[..., 3] = 1.0
    if yaw is not None:
        bs[..., 3] = np.cos(np.asarray(yaw) / 2)[:, None]
        bs[..., 6] = np.sin(np.asarray(yaw) / 2)[:, None]
    bs[:, :, :3] = np.array([0.0, 0.0, 0.9]) if root is None else np.asarray(root)[:, None]
    if vel is not None:
        bs[:, 0, 7:10] = vel
    return bs


# Sampling ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("task", ["heading", "steering", "height", "point_goal"])
def test_sampler_is_deterministic_per_seed(task):
    bs = states(64, root=np.random.default_rng(9).normal(size=(64, 3)))

    def run(seed):
        s = GoalSampler(task, 64, control_hz=30, change_rate=3.0, rng=np.random.default_rng(seed))
        s.reset(None, bs, np.arange(64))
        out = [s.goals.copy()]
        for _ in range(5):
            out += [s.advance(None, bs), s.goals.copy()]
        return out

    a, b, c = run(1), run(1), run(2)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], c[0])


def test_goals_lie_within_their_ranges():
    n, rng = 4000, np.random.default_rng(0)
    bs = states(n)
    heading = GoalSampler("heading", n, 30, 0.0, rng)
    heading.reset(None, bs, np.arange(n))
    assert heading.goals.shape == (n, 2) and heading.goals.dtype == np.float32
    assert heading.goals[:, 0].min() >= -math.pi and heading.goals[:, 0].max() <= math.pi
    assert heading.goals[:, 1].min() >= 0.0 and heading.goals[:, 1].max() <= 3.0
    assert heading.goals[:, 0].min() < -3.0 and heading.goals[:, 1].max() > 2.9  # the whole range is used
    steering = GoalSampler("steering", n, 30, 0.0, rng, ranges={"speed": (1.0, 2.0), "direction": (0.0, 0.5)})
    steering.reset(None, bs, np.arange(n))
    assert np.abs(steering.goals[:, 0]).max() <= math.pi
    assert steering.goals[:, 1].min() >= 0.0 and steering.goals[:, 1].max() <= 0.5
    assert steering.goals[:, 2].min() >= 1.0 and steering.goals[:, 2].max() <= 2.0
    height = GoalSampler("height", n, 30, 0.0, rng)
    height.reset(None, bs, np.arange(n))
    values, counts = np.unique(height.goals, return_counts=True)
    assert values.tolist() == [-1.0, 1.0] and abs(counts[0] / n - 0.5) < 0.05
    with pytest.raises(ValueError, match="unknown goal range 'angle'"):
        GoalSampler("heading", n, 30, 0.0, rng, ranges={"angle": (0.0, 1.0)})
    with pytest.raises(ValueError, match="change_rate must be in"):
        GoalSampler("heading", n, 30, 31.0, rng)


def test_point_goals_are_at_the_drawn_distance_from_the_root():
    n, rng = 2000, np.random.default_rng(1)
    roots = rng.uniform(-10, 10, size=(n, 3))
    sampler = GoalSampler("point_goal", n, 30, 0.0, rng)
    sampler.reset(None, states(n, root=roots), np.arange(n))
    offset = sampler.goals - roots[:, :2]
    distance = np.linalg.norm(offset, axis=-1)
    assert distance.min() >= 1.0 - 1e-5 and distance.max() <= 5.0 + 1e-5
    bearing = np.arctan2(offset[:, 1], offset[:, 0])
    assert np.histogram(bearing, bins=4, range=(-math.pi, math.pi))[0].min() > 0.2 * n  # every quadrant
    # Redrawn goals are drawn from where the roots are now; the others stay.
    sampler = GoalSampler("point_goal", n, 30, 15.0, rng)  # p = 1/2 a step
    sampler.reset(None, states(n, root=roots), np.arange(n))
    before, moved = sampler.goals.copy(), roots + np.array([100.0, 0.0, 0.0])
    changed = sampler.advance(None, states(n, root=moved))
    distance = np.linalg.norm(sampler.goals - moved[:, :2], axis=-1)
    assert 0.4 * n < changed.sum() < 0.6 * n
    assert distance[changed].min() >= 1.0 - 1e-4 and distance[changed].max() <= 5.0 + 1e-4
    np.testing.assert_array_equal(sampler.goals[~changed], before[~changed])


@pytest.mark.parametrize("change_rate", [0.0, 0.42, 3.0])
def test_goals_change_at_the_configured_rate(change_rate):
    # 1000 environments for 300 steps at 30 Hz = 10,000 environment-seconds: change_rate · 10,000
    # changes expected; 4,200 ± 64 (one σ) at 0.42/s, so ±10% is loose.
    n, steps, hz = 1000, 300, 30.0
    sampler = GoalSampler("heading", n, hz, change_rate, np.random.default_rng(3))
    sampler.reset(None, None, np.arange(n))
    changes = 0
    for _ in range(steps):
        before = sampler.goals.copy()
        changed = sampler.advance(None, None)
        assert np.array_equal(before[~changed], sampler.goals[~changed])
        changes += changed.sum()
    expected = change_rate * n * steps / hz
    assert abs(changes - expected) <= 0.1 * expected


def test_sampler_state_round_trip():
    sampler = GoalSampler("steering", 8, 30, 5.0, np.random.default_rng(4))
    sampler.reset(None, None, np.arange(8))
    state = sampler.state_dict()
    first = [(sampler.advance(None, None), sampler.goals.copy()) for _ in range(4)]
    sampler.load_state_dict(state)
    again = [(sampler.advance(None, None), sampler.goals.copy()) for _ in range(4)]
    for (c1, g1), (c2, g2) in zip(first, again, strict=True):
        np.testing.assert_array_equal(c1, c2)
        np.testing.assert_array_equal(g1, g2)
    with pytest.raises(ValueError, match="does not fit"):
        GoalSampler("heading", 8, 30, 5.0, np.random.default_rng(4)).load_state_dict(state)


def reference_vr_points(sim: BatchedSim) -> np.ndarray:
    """[N, 9] head sphere centre (0.175 m up the neck body) and wrists of the simulator's reference now."""
    ref = sim.reference_state()
    head = ref.xpos[:, HEAD] + rot.rotate(ref.xquat[:, HEAD], np.array([0.0, 0.0, 0.175]))
    return np.concatenate((head, ref.xpos[:, LEFT_HAND], ref.xpos[:, RIGHT_HAND]), axis=-1)


def test_vr_goals_follow_the_reference_one_step_ahead(character, walk_run):
    sim = BatchedSim(character, walk_run, num_envs=3, seed=0)
    sampler = GoalSampler("vr", 3, 30, 0.42, np.random.default_rng(0))
    sampler.reset(sim, pack(sim.kin_state()), np.arange(3))
    for _ in range(3):
        goals = sampler.goals.copy()  # the targets of the coming step
        result = sim.step(character.qpos_to_action(sim.reference_state().qpos))
        np.testing.assert_allclose(goals, reference_vr_points(sim), atol=1e-5)
        changed = sampler.advance(sim, pack(result.kin))
        assert not changed.any()
    # A reset environment's goals come from its new reference.
    sim.reset(np.array([1]), clip_ids=np.array([1]), frames=np.array([5]))
    sampler.reset(sim, pack(sim.kin_state()), np.array([1]))
    sim.step(character.qpos_to_action(sim.reference_state().qpos))
    np.testing.assert_allclose(sampler.goals[1], reference_vr_points(sim)[1], atol=1e-5)


# Success -------------------------------------------------------------------------------------------
def vr_episode(
    offsets: np.ndarray, fell_at: int | None = None, all_points: bool = False, fall_fails: bool = True
) -> float:
    """One vr episode of len(offsets) steps, each tracked point `offsets` [T, 3] metres off its target."""
    tracker = SuccessTracker("vr", 1, HZ, all_points=all_points, fall_fails=fall_fails)
    bs = states(1, root=np.array([[0.5, -0.2, 0.9]]))
    head = bs[0, HEAD, :3] + np.array([0.0, 0.0, 0.175])
    on_target = np.concatenate((head, bs[0, LEFT_HAND, :3], bs[0, RIGHT_HAND, :3]))[None]
    for t, off in enumerate(offsets):
        shift = np.zeros((3, 3))
        shift[:, 0] = off  # each target moved along x
        tracker.update(bs, (on_target + shift.ravel()).astype(np.float32), np.array([t == fell_at]))
    return float(tracker.result(np.array([0]))[0])


def test_vr_success_is_pulses_mean_distance_rule():
    steps = np.zeros((30, 3))
    assert vr_episode(steps) == 1.0
    assert vr_episode(steps + 0.45) == 1.0  # every point 0.45 m off: within 0.5 m
    one_frame = steps.copy()
    one_frame[17] = 0.6
    assert vr_episode(one_frame) == 0.0  # one frame 0.6 m off fails the episode
    hand = steps.copy()
    hand[17, 2] = 0.6  # the right hand alone: mean 0.2 m, PULSE's rule passes, all_points fails
    assert vr_episode(hand) == 1.0
    assert vr_episode(hand, all_points=True) == 0.0
    assert vr_episode(steps, fell_at=20) == 0.0  # our clause: a fall fails
    # PULSE's rule alone: a fall fails only through the points' distances.
    assert vr_episode(steps, fell_at=20, fall_fails=False) == 1.0
    lying = steps.copy()
    lying[20:] = 1.2  # the body on the ground after its fall: the head far below its target
    assert vr_episode(lying, fell_at=20, fall_fails=False) == 0.0
    assert SUCCESS_RADIUS_M == 0.5


def run(tracker: SuccessTracker, bs: np.ndarray, goal, steps: int, fell: bool = False, change: bool = False):
    """`steps` identical steps of one environment; the goal changes after the last one if `change`."""
    for t in range(steps):
        changed = np.array([change and t == steps - 1])
        tracker.update(bs, np.asarray([goal], np.float32), np.array([fell]), changed)


def test_point_goal_success_needs_the_root_within_half_a_metre():
    goal = [3.0, 4.0]  # 5 m from the origin
    for final, fell, expected in [(4.6, False, 1.0), (4.4, False, 0.0), (4.6, True, 0.0)]:
        # Walk 60 steps (6 s at 10 Hz) straight to `final` m along the way, then stand.
        tracker = SuccessTracker("point_goal", 1, HZ)
        for t in range(60):
            d = final * min(1.0, t / 40)
            tracker.update(states(1, root=np.array([[0.6 * d, 0.8 * d, 0.9]])), np.array([goal]), np.array([fell]))
        assert tracker.result(np.array([0]))[0] == expected, (final, fell)
    # A goal held for less than 6 s is not judged, reached or not.
    tracker = SuccessTracker("point_goal", 1, HZ)
    run(tracker, states(1, root=np.array([[3.0, 4.0, 0.9]])), goal, 20)
    assert np.isnan(tracker.result(np.array([0]))[0])


def heading_states(facing: float, speed: float, along: float) -> np.ndarray:
    """Facing `facing`, root moving at `speed` along direction `along`."""
    return states(1, yaw=[facing], vel=[speed * math.cos(along), speed * math.sin(along), 0.0])


def test_heading_success_over_the_last_second_of_each_goal():
    goal = [math.pi / 2, 1.0]

    def episode(*segments) -> float:
        tracker = SuccessTracker("heading", 1, HZ)
        for bs, steps, change in segments:
            run(tracker, bs, goal, steps, change=change)
        return float(tracker.result(np.array([0]))[0])

    good = heading_states(math.pi / 2, 1.0, math.pi / 2)
    assert episode((good, 20, False)) == 1.0
    assert episode((heading_states(math.pi / 2 + 0.4, 1.0, math.pi / 2), 20, False)) == 0.0  # 0.4 rad > 0.35
    assert episode((heading_states(math.pi / 2 + 0.3, 1.0, math.pi / 2), 20, False)) == 1.0
    assert episode((heading_states(math.pi / 2, 1.4, math.pi / 2), 20, False)) == 0.0  # 0.4 m/s > 0.3
    assert episode((heading_states(math.pi / 2, 1.2, math.pi / 2), 20, False)) == 1.0
    # Wrong for the first second, right for the last: the first second is the time to respond.
    assert episode((heading_states(0.0, 0.0, 0.0), 10, False), (good, 10, False)) == 1.0
    # A failed goal fails the episode though the next one is met; a goal held < 2 s is not judged.
    assert episode((heading_states(0.0, 0.0, 0.0), 20, True), (good, 20, False)) == 0.0
    assert episode((heading_states(0.0, 0.0, 0.0), 15, True), (good, 20, False)) == 1.0
    assert np.isnan(episode((good, 15, False)))
    tracker = SuccessTracker("heading", 1, HZ)
    run(tracker, good, goal, 20, fell=True)
    assert tracker.result(np.array([0]))[0] == 0.0


def test_steering_judges_the_direction_of_the_mean_velocity():
    # Facing θ_h* = 0, v* = 1 along θ_v* = π/2, swaying ±0.5 m/s sideways every other step: each step's
    # direction is atan(0.5) = 0.46 rad off, more than 0.35, but the second's mean velocity is on course.
    goal = [0.0, math.pi / 2, 1.0]
    tracker = SuccessTracker("steering", 1, HZ)
    for t in range(20):
        bs = states(1, yaw=[0.0], vel=[0.5 * (-1) ** t, 1.0, 0.0])
        tracker.update(bs, np.array([goal]), np.array([False]))
    assert tracker.result(np.array([0]))[0] == 1.0  # planar speed √1.25 = 1.118: error 0.118 < 0.3
    tracker = SuccessTracker("steering", 1, HZ)
    run(tracker, states(1, yaw=[0.0], vel=[1.0, 0.0, 0.0]), goal, 20)  # moving along x: π/2 off
    assert tracker.result(np.array([0]))[0] == 0.0
    # v* = 0: standing still facing θ_h* meets it, whatever the direction of the root's drift.
    tracker = SuccessTracker("steering", 1, HZ)
    run(tracker, states(1, yaw=[0.0], vel=[-0.05, 0.0, 0.0]), [0.0, math.pi / 2, 0.0], 20)
    assert tracker.result(np.array([0]))[0] == 1.0


def test_height_success_and_falls_do_not_count():
    def episode(h: float, goal: float, fell: bool = False) -> float:
        tracker = SuccessTracker("height", 1, HZ)
        run(tracker, states(1, root=np.array([[0.0, 0.0, h]])), [goal], 20, fell=fell)
        return float(tracker.result(np.array([0]))[0])

    assert episode(0.85, 1.0) == 1.0 and episode(0.75, 1.0) == 0.0
    assert episode(0.2, -1.0, fell=True) == 1.0 and episode(0.45, -1.0) == 0.0
    assert episode(0.85, -1.0) == 0.0
    assert HEIGHT_HIGH_M == 0.8


def test_tracker_tracks_environments_apart_and_resets():
    tracker = SuccessTracker("height", 2, HZ)
    bs = states(2, root=np.array([[0.0, 0.0, 0.9], [0.0, 0.0, 0.3]]))
    for _ in range(20):
        tracker.update(bs, np.array([[1.0], [1.0]], np.float32), np.zeros(2, bool))
    np.testing.assert_array_equal(tracker.result(np.arange(2)), [1.0, 0.0])
    state = tracker.state_dict()
    tracker.reset(np.array([1]))
    assert np.isnan(tracker.result(np.array([1]))[0]) and tracker.result(np.array([0]))[0] == 1.0
    tracker.load_state_dict(state)
    np.testing.assert_array_equal(tracker.result(np.arange(2)), [1.0, 0.0])
