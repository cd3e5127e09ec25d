"""The replay buffer: windows of consecutive transitions, eviction, checkpoints, errors.

The trajectories here come from a fake process whose states spell out where they
come from: every entry of a body state holds a code of (worker, env, k), k the
stream's time. A step moves k to k+1; a reset jumps it by 1000. So a window is
consecutive exactly when its L+1 codes are one stream's k0, k0+1, ..., k0+L.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from workers.replay.buffer import ReplayBuffer
from workers.types import Trajectory

B, A = 2, 3
RESET_JUMP = 1000


def code(worker, env, k):
    return worker * 1_000_000 + env * 100_000 + k


def decode(x):
    x = np.asarray(x, np.int64)
    return x // 1_000_000, (x // 100_000) % 10, x % 100_000


class FakeWorker:
    """M streams stepping k -> k+1, reset (k -> k + 1000) with probability p_done after a step."""

    def __init__(self, worker: int, num_envs: int, p_done: float = 0.0, seed: int = 0):
        self.worker, self.m, self.p_done = worker, num_envs, p_done
        self.k = np.zeros(num_envs, np.int64)
        self.rng = np.random.default_rng(seed)
        self.version = 0

    def collect(self, steps: int, keep: np.ndarray | None = None) -> Trajectory:
        env = np.arange(self.m)
        states, nexts, done = [], [], []
        for _ in range(steps):
            states.append(code(self.worker, env, self.k))
            nexts.append(code(self.worker, env, self.k + 1))
            d = self.rng.random(self.m) < self.p_done
            done.append(d)
            self.k = np.where(d, self.k + RESET_JUMP, self.k + 1)
        states, nexts = np.array(states), np.array(nexts)  # [T, M] codes

        def body(c):
            return np.broadcast_to(c[..., None, None], c.shape + (B, 13)).astype(np.float32)

        traj = Trajectory(
            states=body(states),
            next_states=body(nexts),
            actions=np.broadcast_to(states[..., None], states.shape + (A,)).astype(np.float32),
            done=np.array(done),
            clip_id=np.zeros(states.shape, np.int64),
            frame=decode(states)[2],
            version=self.version,
            worker=self.worker,
        )
        self.version += 1
        return traj


def window_codes(batch) -> np.ndarray:
    """Codes [n, L+1] of the windows' states (float32 holds these integers exactly)."""
    codes = batch.states[..., 0, 0].astype(np.int64)
    assert (batch.states == batch.states[..., :1, :1]).all()
    return codes


def assert_consecutive(batch, length):
    codes = window_codes(batch)
    assert codes.shape[1] == length + 1
    np.testing.assert_array_equal(np.diff(codes, axis=1), 1)  # one stream, no reset, no gap
    np.testing.assert_array_equal(batch.actions[..., 0], codes[:, :-1])  # actions line up with states
    np.testing.assert_array_equal(batch.frame, decode(codes[:, 0])[2])


def brute_force_starts(buf: ReplayBuffer, length: int) -> set[int]:
    """Codes of the states at which a window starts, by definition: k0 .. k0+L-1 all stored, and the
    transitions from k0 .. k0+L-2 did not reset (a reset's successor code is never stored)."""
    stored = set(buf._states[: len(buf), 0, 0].astype(np.int64).tolist())
    return {c for c in stored if all(c + j in stored for j in range(length))}


def test_windows_never_cross_streams_resets_or_pushes_badly():
    buf = ReplayBuffer(10_000, B, A, seed=0)
    workers = [FakeWorker(0, 3, p_done=0.1, seed=1), FakeWorker(1, 3, p_done=0.1, seed=2)]
    for _ in range(6):
        for w in workers:
            buf.add(w.collect(5))
    assert len(buf) == buf.num_added == 2 * 6 * 5 * 3
    for length in (1, 3, 7, 12):  # longer than one push (5): windows run across pushes
        starts = buf.valid_starts(length)
        got = set(buf._states[starts, 0, 0].astype(np.int64).tolist())
        assert got == brute_force_starts(buf, length)
        assert len(got) > 0
        assert_consecutive(buf.sample_windows(300, length), length)


def test_window_may_end_on_a_reset_with_its_true_successor():
    buf = ReplayBuffer(100, B, A)
    w = FakeWorker(0, 1)
    traj = w.collect(4)
    traj.done[3, 0] = True  # the last transition ends the episode
    buf.add(traj)
    batch = buf.sample_windows(5, 4)
    # Hand-worked: the only window is k = 0..3 followed by the true successor k = 4.
    np.testing.assert_array_equal(window_codes(batch), np.tile(np.arange(5), (5, 1)))
    traj.done[1, 0] = True  # a reset inside: no window of 4 is left
    buf2 = ReplayBuffer(100, B, A)
    buf2.add(traj)
    assert len(buf2.valid_starts(4)) == 0
    assert len(buf2.valid_starts(2)) == 2  # (0, 1) and (2, 3)


def test_a_lost_push_or_a_restart_is_a_gap():
    buf = ReplayBuffer(1000, B, A)
    w = FakeWorker(0, 2)
    buf.add(w.collect(4))
    w.collect(4)  # lost on its way: k = 4..7 never arrive
    buf.add(w.collect(4))
    assert len(buf.valid_starts(5)) == 0
    assert len(buf.valid_starts(4)) == 4  # two per env, one per push
    # A worker that restarts from scratch (same id, k back to 0) does not continue its old stream.
    buf2 = ReplayBuffer(1000, B, A)
    buf2.add(FakeWorker(0, 1).collect(3))
    buf2.add(FakeWorker(0, 1).collect(3))
    assert len(buf2.valid_starts(4)) == 0
    steps = buf2._step[:6]
    assert steps.tolist() == [0, 1, 2, 4, 5, 6]  # the stream's step index jumps at the gap


def test_eviction_keeps_the_newest_and_cuts_windows():
    capacity = 50
    buf = ReplayBuffer(capacity, B, A, seed=3)
    w = FakeWorker(0, 2)
    all_codes = []
    for _ in range(9):  # 9 pushes of 2 × 4 = 72 transitions > 50
        traj = w.collect(4)
        all_codes.append(traj.states[..., 0, 0].astype(np.int64).T.ravel())  # env-major, as stored
        buf.add(traj)
    assert len(buf) == capacity and buf.num_added == 72
    newest = np.concatenate(all_codes)[-capacity:]
    stored = buf._states[:, 0, 0].astype(np.int64)
    assert set(stored.tolist()) == set(newest.tolist())
    for length in (2, 6, 10):
        assert set(buf._states[buf.valid_starts(length), 0, 0].astype(np.int64).tolist()) == brute_force_starts(
            buf, length
        )
        batch = buf.sample_windows(200, length)
        assert_consecutive(batch, length)
        assert set(window_codes(batch)[:, :-1].ravel().tolist()) <= set(newest.tolist())
    assert buf.stats()["oldest_version"] > 0  # the first pushes are gone


def test_state_dict_round_trip_gives_identical_samples():
    buf = ReplayBuffer(60, B, A, seed=7)
    w = FakeWorker(2, 3, p_done=0.05, seed=4)
    for _ in range(5):
        buf.add(w.collect(4))
    state = copy.deepcopy(buf.state_dict())
    other = ReplayBuffer(60, B, A, seed=123)
    other.load_state_dict(state)
    assert other.stats() == buf.stats()
    for _ in range(3):
        a, b = buf.sample_windows(16, 5), other.sample_windows(16, 5)
        np.testing.assert_array_equal(a.states, b.states)
        np.testing.assert_array_equal(a.version, b.version)
        np.testing.assert_array_equal(buf.sample_states(8)[0], other.sample_states(8)[0])
    traj = w.collect(4)  # the restored buffer also links new pushes to the old streams
    buf.add(traj)
    other.add(copy.deepcopy(traj))
    np.testing.assert_array_equal(buf.sample_windows(32, 8).states, other.sample_windows(32, 8).states)


def test_a_checkpoint_stores_only_the_next_states_that_are_not_their_successors_and_restores_all_exactly():
    buf = ReplayBuffer(60, B, A, seed=7)
    w = FakeWorker(2, 3, p_done=0.05, seed=4)
    for _ in range(8):  # 96 transitions into 60 slots: the oldest overwritten, links into them stale
        buf.add(w.collect(4))
    state = buf.state_dict()
    kept, same = state["arrays"]["next_states"], state["arrays"]["next_states_same"]
    assert len(kept) == int((~same).sum())
    assert 3 <= len(kept) <= 15  # each stream's newest step, a reset's, a stale link's: a few of 60
    other = ReplayBuffer(60, B, A, seed=123)
    other.load_state_dict(copy.deepcopy(state))
    for key in ReplayBuffer._ARRAYS:
        np.testing.assert_array_equal(getattr(other, "_" + key), getattr(buf, "_" + key), err_msg=key)
    # A checkpoint that stored every next state (before this) loads the same.
    full = copy.deepcopy(state)
    full["arrays"]["next_states"] = buf._next_states[:60].copy()
    del full["arrays"]["next_states_same"]
    older = ReplayBuffer(60, B, A)
    older.load_state_dict(full)
    np.testing.assert_array_equal(older._next_states, buf._next_states)


def test_nbytes_is_what_the_buffer_allocates():
    buf = ReplayBuffer(37, B, A)
    allocated = sum(v.nbytes for v in vars(buf).values() if isinstance(v, np.ndarray))
    assert ReplayBuffer.nbytes(37, B, A) == allocated


def test_sample_states_and_stats():
    buf = ReplayBuffer(100, B, A)
    w = FakeWorker(0, 2)
    buf.add(w.collect(3))  # version 0
    buf.add(w.collect(3))  # version 1
    states, clip_id, frame = buf.sample_states(10)
    assert states.shape == (10, B, 13) and clip_id.shape == frame.shape == (10,)
    np.testing.assert_array_equal(decode(states[:, 0, 0])[2], frame)
    stats = buf.stats()
    # Hand-worked: 12 of 100 stored, versions six 0s and six 1s.
    assert stats["size"] == 12 and stats["fill"] == pytest.approx(0.12)
    assert (stats["oldest_version"], stats["newest_version"], stats["mean_version"]) == (0.0, 1.0, 0.5)


def test_errors_are_clear():
    buf = ReplayBuffer(20, B, A)
    with pytest.raises(ValueError, match="no window of 3 consecutive transitions"):
        buf.sample_windows(4, 3)
    with pytest.raises(ValueError, match="empty"):
        buf.sample_states(4)
    buf.add(FakeWorker(0, 1).collect(2))
    with pytest.raises(ValueError, match=r"no window of 3 .*2 transitions stored"):
        buf.sample_windows(4, 3)
    with pytest.raises(ValueError, match="at least 1"):
        buf.sample_windows(4, 0)
    with pytest.raises(ValueError, match="does not fit"):
        buf.add(FakeWorker(0, 3).collect(7))
    bad = FakeWorker(0, 1).collect(2)
    bad.actions = bad.actions[..., :2]
    with pytest.raises(ValueError, match=r"trajectory.actions must be \[2, 1, 3\]"):
        buf.add(bad)
    with pytest.raises(ValueError, match="capacity"):
        ReplayBuffer(21, B, A).load_state_dict(buf.state_dict())
    with pytest.raises(ValueError, match="capacity"):
        ReplayBuffer(0, B, A)
