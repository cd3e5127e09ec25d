"""The replay buffer: a ring of simulated transitions, handed out as windows of consecutive steps.

Rollout workers push `Trajectory`s (`workers.types`: T steps of M environments). Every
environment of every worker is a *stream*, identified by (worker, env). The
buffer stores each stream's T transitions of one push contiguously, and links
each transition to its successor in the same stream:

- inside a push, transition t links to t+1 unless the environment was reset
  after t (done[t]) or its reference clip was switched after t (the extra
  `switched[t]`: the next state is the same body, but the reference it is paired
  with jumps, so no window crosses a switch);
- across pushes, the last transition of a stream's previous push links to the
  first of its new push when the former is still stored, was not done, and its
  true successor is bit for bit the new first state (so a worker that restarted,
  or a push that was lost, leaves a gap that no window crosses);
- links always point from an older transition to a newer one, and slots are
  overwritten oldest first, so a link never outlives its target: the slot it
  leaves from was overwritten (and its links rewritten) first.

A window of L transitions starts at any stored transition with L-1 successive
links. Its states are the L states plus the true successor of the last one, so
the last transition may be a done one (its successor is the real next state,
taken before the reset). Windows therefore never straddle two streams, a reset
or a gap, and can be longer than one push.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from workers.replay.balancing import discounted_returns
from workers.types import StartBatch, Trajectory, WindowBatch

_STREAM_SHIFT = 32  # stream id = worker << 32 | env


class ReplayBuffer:
    """A ring of `capacity` transitions; the oldest are evicted first."""

    def __init__(self, capacity: int, num_bodies: int, action_dim: int, seed: int = 0):
        if capacity < 1:
            raise ValueError(f"replay capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self.num_bodies = num_bodies
        self.action_dim = action_dim
        self.rng = np.random.default_rng(seed)
        c = capacity
        self._states = np.zeros((c, num_bodies, 13), np.float32)
        self._next_states = np.zeros((c, num_bodies, 13), np.float32)
        self._actions = np.zeros((c, action_dim), np.float32)
        self._done = np.zeros(c, bool)  # the link to the next transition is cut (episode end or clip switch)
        self._reward = np.zeros(c, np.float32)
        self._clip_id = np.zeros(c, np.int64)
        self._frame = np.zeros(c, np.int64)
        self._version = np.zeros(c, np.int64)
        self._stream = np.zeros(c, np.int64)
        self._step = np.zeros(c, np.int64)  # position in its stream, counted by the buffer
        self._uid = np.full(c, -1, np.int64)  # which transition ever added (num_added order) the slot holds
        self._next = np.full(c, -1, np.int64)  # slot of the successor in the same stream, -1 if none
        self._ptr = 0
        self._size = 0
        self.num_added = 0
        # stream id -> (slot, uid, step) of its newest transition
        self._last: dict[int, tuple[int, int, int]] = {}
        self._valid_starts: dict[int, np.ndarray] = {}  # window length -> valid start slots (cache)

    @staticmethod
    def nbytes(capacity: int, num_bodies: int, action_dim: int) -> int:
        """The memory the arrays of a buffer of `capacity` transitions take (what `__init__` allocates): two
        float32 body states, a float32 action and reward, a done flag and seven int64 indices per transition."""
        return capacity * (2 * num_bodies * 13 * 4 + action_dim * 4 + 4 + 1 + 7 * 8)

    def __len__(self) -> int:
        return self._size

    # Adding ------------------------------------------------------------------
    def add(self, traj: Trajectory) -> None:
        """Store the T·M transitions of a trajectory, each environment's T steps contiguously."""
        t_len, m = traj.done.shape
        n = t_len * m
        b, a = self.num_bodies, self.action_dim
        expected = {
            "states": (t_len, m, b, 13),
            "next_states": (t_len, m, b, 13),
            "actions": (t_len, m, a),
            "clip_id": (t_len, m),
            "frame": (t_len, m),
        }
        for name, shape in expected.items():
            if getattr(traj, name).shape != shape:
                raise ValueError(f"trajectory.{name} must be {list(shape)}, got {list(getattr(traj, name).shape)}")
        if n > self.capacity:
            raise ValueError(f"a trajectory of {n} transitions does not fit a replay buffer of {self.capacity}")
        if n == 0:
            return
        pos = (self._ptr + np.arange(n)) % self.capacity  # env-major: env e's steps at pos[e*T : (e+1)*T]

        def env_major(x: np.ndarray) -> np.ndarray:
            return np.swapaxes(x, 0, 1).reshape((n,) + x.shape[2:])

        cut = np.asarray(traj.done, bool) | np.asarray(traj.extras.get("switched", False), bool)
        done = env_major(cut)
        reward = traj.extras.get("reward")
        self._reward[pos] = 0.0 if reward is None else env_major(np.asarray(reward, np.float32))
        self._states[pos] = env_major(traj.states)
        self._next_states[pos] = env_major(traj.next_states)
        self._actions[pos] = env_major(traj.actions)
        self._done[pos] = done
        self._clip_id[pos] = env_major(traj.clip_id)
        self._frame[pos] = env_major(traj.frame)
        self._version[pos] = traj.version
        streams = (np.int64(traj.worker) << _STREAM_SHIFT) | np.arange(m, dtype=np.int64)
        self._stream[pos] = np.repeat(streams, t_len)
        self._uid[pos] = self.num_added + np.arange(n)
        # Links inside the push: each step to the next one of the same env, unless reset.
        grid = pos.reshape(m, t_len)
        nxt = np.full((m, t_len), -1, np.int64)
        nxt[:, :-1] = np.where(done.reshape(m, t_len)[:, :-1], -1, grid[:, 1:])
        self._next[pos] = nxt.ravel()
        # Links across pushes. Step indices count along the stream and jump by 2 where a link is cut
        # (a reset or a gap), so that consecutive indices within one stream mean linked transitions.
        jumps = np.ones((m, t_len), np.int64)
        jumps[:, 1:] += done.reshape(m, t_len)[:, :-1]
        for e, stream in enumerate(streams.tolist()):
            first = int(grid[e, 0])
            base = -1
            if stream in self._last:
                slot, uid, last_step = self._last[stream]
                linked = (
                    self._uid[slot] == uid
                    and not self._done[slot]
                    and np.array_equal(self._next_states[slot], self._states[first])
                )
                if linked:
                    self._next[slot] = first
                base = last_step + (0 if linked else 1)
            jumps[e, 0] = base + 1
        steps = np.cumsum(jumps, axis=1)
        self._step[pos] = steps.ravel()
        for e, stream in enumerate(streams.tolist()):
            self._last[stream] = (int(grid[e, -1]), int(self._uid[grid[e, -1]]), int(steps[e, -1]))
        self._ptr = int((self._ptr + n) % self.capacity)
        self._size = min(self._size + n, self.capacity)
        self.num_added += n
        self._valid_starts.clear()

    # Sampling ----------------------------------------------------------------
    def valid_starts(self, length: int) -> np.ndarray:
        """Slots [W] at which a window of `length` consecutive transitions starts."""
        if length < 1:
            raise ValueError(f"window length must be at least 1, got {length}")
        if length not in self._valid_starts:
            # Follow the links length-1 times from every stored slot at once.
            ok = np.ones(self._size, bool)
            cur = np.arange(self._size)  # slots [0, size) are the filled ones
            for _ in range(length - 1):
                nxt = self._next[cur]
                ok &= nxt >= 0
                cur = np.where(ok, nxt, cur)
            self._valid_starts[length] = np.flatnonzero(ok)
        return self._valid_starts[length]

    def window_slots(self, starts: np.ndarray, length: int) -> np.ndarray:
        """Slots [n, length] of the windows that start at `starts` (which must be valid)."""
        slots = np.empty((len(starts), length), np.int64)
        slots[:, 0] = starts
        for k in range(1, length):
            slots[:, k] = self._next[slots[:, k - 1]]
        return slots

    def sample_windows(self, n: int, length: int) -> WindowBatch:
        """n windows of `length` consecutive transitions, drawn uniformly (with replacement) among the valid ones."""
        starts = self.valid_starts(length)
        if len(starts) == 0:
            raise ValueError(
                f"no window of {length} consecutive transitions in the replay buffer "
                f"({self._size} transitions stored); collect more, or use shorter windows"
            )
        starts = starts[self.rng.integers(len(starts), size=n)]
        slots = self.window_slots(starts, length)
        states = np.concatenate((self._states[slots], self._next_states[slots[:, -1:]]), axis=1)
        return WindowBatch(
            states=states,
            actions=self._actions[slots],
            clip_id=self._clip_id[starts],
            frame=self._frame[starts],
            version=self._version[starts],
        )

    def sample_states(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(states [n, B, 13], clip_id [n], frame [n]) of stored transitions drawn uniformly."""
        if self._size == 0:
            raise ValueError("cannot sample states from an empty replay buffer")
        idx = self.rng.integers(self._size, size=n)
        return self._states[idx], self._clip_id[idx], self._frame[idx]

    def discounted_returns(
        self, gamma: float, bootstrap: Callable[[np.ndarray, np.ndarray], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Data balancing's V* (ControlVAE Eq. 18) of every stored transition: (clip_id, frame, V*), [size] each.

        Rewards are the stored ones; a trajectory ends where its links do, and is bootstrapped there
        with `bootstrap(clip_id, frame)` [n] of the reference frame after its last state.
        """
        size = self._size
        clip, frame, successor = self._clip_id[:size], self._frame[:size], self._next[:size]
        ends = np.flatnonzero(successor < 0)
        boot = np.zeros(size)
        boot[ends] = bootstrap(clip[ends], frame[ends] + 1)
        order = np.argsort(self._uid[:size], kind="stable")
        g = discounted_returns(self._reward[:size].astype(np.float64), successor, order, boot, gamma)
        return clip.copy(), frame.copy(), g

    def sample_starts(self, n: int, norm_states: int) -> StartBatch:
        """n stored states drawn uniformly (any of them: the last ones before an episode end too, which no
        window of more than one step starts at) and `norm_states` more for input statistics."""
        states, clip_id, frame = self.sample_states(n)
        return StartBatch(states, clip_id, frame, self.sample_states(norm_states)[0])

    # Reporting -----------------------------------------------------------------
    def stats(self) -> dict[str, float]:
        """Size, fill fraction, total added, and the policy versions of what is stored."""
        out = {
            "size": float(self._size),
            "fill": self._size / self.capacity,
            "num_added": float(self.num_added),
        }
        if self._size:
            v = self._version[: self._size]
            out.update(newest_version=float(v.max()), oldest_version=float(v.min()), mean_version=float(v.mean()))
        else:
            out.update(newest_version=-1.0, oldest_version=-1.0, mean_version=-1.0)
        return out

    # Checkpoints -----------------------------------------------------------------
    _ARRAYS = "states next_states actions done reward clip_id frame version stream step uid next".split()

    def state_dict(self) -> dict[str, Any]:
        """The stored transitions, links, counters and RNG state: NumPy arrays and plain types only."""
        size = self._size
        last = np.array([(k, *v) for k, v in self._last.items()], np.int64).reshape(-1, 4)
        arrays = {k: getattr(self, "_" + k)[:size].copy() for k in self._ARRAYS}
        # A transition's next state is, bit for bit, its successor's state nearly always: only the others are
        # stored (`next_states_same` marks the rest), which halves the file.
        states, successor = arrays["states"], arrays["next"]
        linked = (successor >= 0) & (successor < size)
        same = np.zeros(size, bool)
        same[linked] = (arrays["next_states"][linked] == states[successor[linked]]).all(axis=(1, 2))
        arrays["next_states"] = arrays["next_states"][~same]
        arrays["next_states_same"] = same
        return {
            "capacity": self.capacity,
            "num_bodies": self.num_bodies,
            "action_dim": self.action_dim,
            "arrays": arrays,
            "last": last,
            "ptr": self._ptr,
            "size": size,
            "num_added": self.num_added,
            "rng": self.rng.bit_generator.state,  # plain dict of str and int
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        shape = (state["capacity"], state["num_bodies"], state["action_dim"])
        if shape != (self.capacity, self.num_bodies, self.action_dim):
            raise ValueError(
                f"replay state is for (capacity, bodies, action_dim) = {shape}, "
                f"this buffer is {(self.capacity, self.num_bodies, self.action_dim)}"
            )
        size = int(state["size"])
        arrays = dict(state["arrays"])
        same = arrays.pop("next_states_same", None)  # absent from checkpoints that stored every next state
        if same is not None:
            same = np.asarray(same, bool)
            full = np.empty((size, self.num_bodies, 13), np.float32)
            full[same] = arrays["states"][arrays["next"][same]]
            full[~same] = arrays["next_states"]
            arrays["next_states"] = full
        for k in self._ARRAYS:
            arr = getattr(self, "_" + k)
            arr[:size] = arrays.get(k, 0)  # rewards are absent from older checkpoints
            arr[size:] = -1 if k in ("uid", "next") else 0
        self._last = {int(k): (int(s), int(u), int(t)) for k, s, u, t in np.asarray(state["last"]).reshape(-1, 4)}
        self._ptr = int(state["ptr"])
        self._size = size
        self.num_added = int(state["num_added"])
        self.rng.bit_generator.state = state["rng"]
        self._valid_starts.clear()
