"""ControlVAE's collection (§3.4.3–3.4.4): data balancing, clip switches, single-state VAE starts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.learners.base import Weights
from workers.learners.vae import ControlVAEObjective, VAEConfig, build_controller, state_weight_vector
from workers.motion.library import MotionLibrary, balancing_weights
from workers.policies import VAEPolicy
from workers.recorders import TrackingReward
from workers.replay.balancing import (
    FrameValues,
    discounted_returns,
    frame_sums,
    library_rows,
)
from workers.replay.buffer import ReplayBuffer
from workers.rewards import tracking_reward
from workers.rollout import RolloutWorker
from workers.types import Trajectory

SMALL = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(64,))


def test_reward_of_eq_20_by_hand():
    s = np.zeros((2, 4))
    ref = s.copy()
    ref[1, 2] = 1.0  # one feature off by 1, weighted 2: ‖W(s̃ − s)‖₁ = 2
    w = np.array([1.0, 1.0, 2.0, 0.0])
    np.testing.assert_allclose(tracking_reward(s, ref, w), [1.0, np.exp(-2 / 20)], rtol=1e-6)
    ref[0, 3] = 5.0  # a feature of weight zero changes nothing
    assert tracking_reward(s, ref, w)[0] == pytest.approx(1.0)


def test_discounted_returns_and_moving_average_by_hand():
    """Eq. 18 on two trajectories, [0 -> 1 -> 2] and [3 -> 4], given in an order where successors come later."""
    reward = np.array([1.0, 0.5, 0.25, 0.8, 0.4])
    successor = np.array([1, 2, -1, 4, -1])
    bootstrap = np.array([0, 0, 2.0, 0, 1.0])  # V of the frame after each trajectory's last state
    g = discounted_returns(reward, successor, np.arange(5), bootstrap, gamma=0.5)
    # G2 = 0.25 + 0.5 * 2 = 1.25; G1 = 0.5 + 0.5 * 1.25 = 1.125; G0 = 1 + 0.5 * 1.125 = 1.5625
    # G4 = 0.4 + 0.5 * 1 = 0.9; G3 = 0.8 + 0.5 * 0.9 = 1.25
    np.testing.assert_allclose(g, [1.5625, 1.125, 1.25, 1.25, 0.9])
    # Eq. 19: frames 0..2 of a library of 4 frames; frame 1 is seen twice (V* 1.125 and 0.9), frame 3 never.
    values = FrameValues(4, rate=0.5)
    count, total = frame_sums(np.array([0, 1, 2, 2, 1]), g, 4)
    np.testing.assert_array_equal(count, [1, 2, 2, 0])
    assert list(values.update(count, total)) == [0, 1, 2]
    np.testing.assert_allclose(values.values, [0.78125, (1.125 + 0.9) / 4, (1.25 + 1.25) / 4, 0.0])
    values.update(count, total)  # the same returns again: halfway from there toward the target
    np.testing.assert_allclose(values.values[0], 0.78125 * 0.5 + 1.5625 * 0.5)
    # Starts ∝ 1 / max(0.01, V): the frame never seen (V = 0) is the most likely start.
    np.testing.assert_allclose(values.weights(), 1 / np.maximum(0.01, values.values))
    state = values.state_dict()
    again = FrameValues(4)
    again.load_state_dict(state)
    np.testing.assert_array_equal(again.values, values.values)
    assert again.refreshes == 2


def test_low_value_frames_are_drawn_more_often_in_proportion(walk_run):
    lib = MotionLibrary(walk_run.character, walk_run.clips)  # its own start weights
    rng = np.random.default_rng(0)
    values = np.full(lib.total_frames, 2.0)
    values[5] = 0.5  # four times less value: four times the start weight of any other frame
    values[40] = 0.001  # below the floor of 0.01: counted as 0.01, so 200 times
    lib.set_frame_weights(balancing_weights(values))
    clips, frames = lib.sample_starts(200_000, rng)
    rows = library_rows(lib, clips, frames)
    counts = np.bincount(rows, minlength=lib.total_frames)
    usable = lib.total_frames - np.sum(~lib.loop)  # one-shot clips' last frames are never starts
    others = np.delete(counts, [5, 40]).mean() * (lib.total_frames - 2) / (usable - 2)
    assert counts[5] / others == pytest.approx(4.0, rel=0.1)
    assert counts[40] / others == pytest.approx(200.0, rel=0.05)


def test_replay_returns_follow_its_links_and_cut_at_switches():
    """Two environments, 3 steps: env 0 is switched after step 0, env 1 ends after step 1."""
    buffer = ReplayBuffer(100, 1, 1)
    states = np.arange(6, dtype=np.float32).reshape(3, 2)[..., None, None] * np.ones((1, 1, 1, 13), np.float32)
    traj = Trajectory(
        states=states,
        next_states=states + 10,
        actions=np.zeros((3, 2, 1), np.float32),
        done=np.array([[False, False], [False, True], [False, False]]),
        clip_id=np.zeros((3, 2), int),
        frame=np.array([[0, 10], [20, 11], [21, 0]]),  # env 0 jumps from frame 0 to 20: the switch
        version=0,
        worker=0,
        extras={
            "reward": np.full((3, 2), 0.5, np.float32),
            "switched": np.array([[True, False], [False, False], [False, False]]),
        },
    )
    buffer.add(traj)
    # No window of two steps crosses the switch (env 0: 0 -> 20) or the reset (env 1: 11 -> 0).
    for start in buffer.valid_starts(2):
        slots = buffer.window_slots(np.array([start]), 2)[0]
        assert buffer._frame[slots[1]] == buffer._frame[slots[0]] + 1
    seen = []
    clip, frame, g = buffer.discounted_returns(0.5, lambda c, f: seen.append(f.copy()) or np.full(len(f), 4.0))
    # Trajectories: env 0 [0] (cut by the switch) and [20, 21] (newest), env 1 [10, 11] (ended) and [0].
    # Each one's last state bootstraps with V = 4 of the frame after it: 0.5 + 0.5 * 4 = 2.5; the state
    # before it 0.5 + 0.5 * 2.5 = 1.75.
    assert sorted(seen[0].tolist()) == [1, 1, 12, 22]
    got = sorted(zip(frame.tolist(), g.tolist(), strict=True))
    assert got == [(0, 2.5), (0, 2.5), (10, 1.75), (11, 2.5), (20, 1.75), (21, 2.5)]
    assert (clip == 0).all()


def test_single_state_starts_include_the_states_just_before_an_episode_end():
    buffer = ReplayBuffer(1000, 1, 1, seed=0)
    t, m = 40, 4
    done = np.zeros((t, m), bool)
    done[9::10] = True  # episodes of 10 steps
    frame = np.tile(np.arange(t)[:, None] % 10, (1, m))
    states = np.zeros((t, m, 1, 13), np.float32)
    buffer.add(Trajectory(states, states, np.zeros((t, m, 1), np.float32), done, np.zeros((t, m), int), frame, 0, 0))
    # Windows of 4 steps never start on an episode's last three states (frames 7, 8, 9).
    window_frames = set(buffer._frame[buffer.valid_starts(4)].tolist())
    assert window_frames == set(range(7))
    batch = buffer.sample_starts(2000, 50)
    assert set(batch.frame.tolist()) == set(range(10))  # single states: every one of them
    assert batch.states.shape == (2000, 1, 13) and batch.norm_states.shape == (50, 1, 13)


@pytest.fixture(scope="module")
def weights(character) -> Weights:
    torch.manual_seed(11)
    controller = build_controller(character.num_bodies, character.num_actions, SMALL)
    return Weights(1, {k: v.clone() for k, v in controller.state_dict().items()})


def test_switches_happen_at_the_configured_rate_and_windows_never_cross_them(character, walk_run, weights):
    policy = VAEPolicy(character.num_bodies, character.num_actions, SMALL, 0.0)
    w = state_weight_vector(character.num_bodies, ControlVAEObjective().state_weights).numpy()
    worker = RolloutWorker(character, walk_run, 8, policy, seed=1, recorders=[TrackingReward(w)], switch_rate=3.0)
    worker.set_weights(weights)
    traj = worker.collect(150)
    switched = traj.extras["switched"]
    assert traj.extras["switches"] == switched.sum()
    assert not (switched & traj.done).any()  # a finished environment is reset, not switched
    # 3 switches a second at 30 Hz: p = 0.1 per running step (binomial, 4 standard deviations).
    running = (~traj.done).sum()
    expected = 0.1 * running
    assert abs(switched.sum() - expected) < 4 * np.sqrt(expected * 0.9)
    # A fall within 2 s after a switch counts against it, 2 s without one as a recovery; each switch at most once.
    assert traj.extras["switch_falls"] + traj.extras["switch_recoveries"] <= switched.sum()
    assert traj.extras["switch_falls"] > 0  # the untrained controller falls
    # The reference moves on frame by frame, except across a switch or a reset.
    nxt = traj.frame[1:] == traj.frame[:-1] + 1
    same = traj.clip_id[1:] == traj.clip_id[:-1]
    assert ((nxt & same) | switched[:-1] | traj.done[:-1]).all()
    # Eq. 20's reward of each stored state against its (new) reference: 1 on the reference itself.
    reward = traj.extras["reward"]
    assert ((reward > 0) & (reward <= 1)).all()
    starts = np.zeros_like(traj.done)
    starts[1:] = traj.done[:-1]
    np.testing.assert_allclose(reward[starts], 1.0, atol=1e-4)
    buffer = ReplayBuffer(10_000, character.num_bodies, character.num_actions)
    buffer.add(traj)
    for start in buffer.valid_starts(4):
        slots = buffer.window_slots(np.array([start]), 4)[0]
        assert (np.diff(buffer._frame[slots]) == 1).all() and (buffer._clip_id[slots] == buffer._clip_id[start]).all()
    np.testing.assert_allclose(buffer._reward[: len(buffer)].sum(), reward.sum(), rtol=1e-5)
