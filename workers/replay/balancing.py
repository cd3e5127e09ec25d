"""ControlVAE's data balancing (§3.4.3, Eq. 18–20): a value per library frame, and starts drawn ∝ 1/V.

- Eq. 20, the reward of a simulated state s_t against its reference s̃_t:
  r_t = exp(−‖W(s̃_t − s_t)‖₁ / T_V), with W the reconstruction loss's feature
  weights (Eq. 16) and T_V = 20. Its mean over the collected states is also the
  paper's learning curve. `workers.rewards.tracking_reward` computes it, and
  `workers.recorders.TrackingReward` records it for every collected state.
- Eq. 18, the discounted return of a state along its simulated trajectory,
  bootstrapped at the trajectory's end with the value of the reference frame after
  its last state: V*_t = Σ_{k=0}^{T−t} γ^k r_{t+k} + γ^{T+1−t} V_{T+1} (γ = 0.95).
  `discounted_returns` computes it for every stored transition of the replay buffer
  by following its links (a trajectory ends where a link does: an episode end, a
  clip switch, a gap, or the newest transition of a stream).
- Eq. 19, V_t ← (1 − α)V_t + α V*_t for every frame seen (the mean V* of its
  visits); the paper refreshes every 200 iterations and does not give α.
- Starts are then drawn ∝ 1 / max(0.01, V_t) (`MotionLibrary.set_frame_weights`
  with `balancing_weights`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.motion.library import MotionLibrary, balancing_weights


def library_rows(library: MotionLibrary, clip_ids: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """The library's flat frame index of (clip, frame): cyclic clips wrap, one-shot clips clamp."""
    return library.rows(np.asarray(clip_ids, int), np.asarray(frames, int))[0]


def discounted_returns(
    reward: np.ndarray, successor: np.ndarray, order: np.ndarray, bootstrap: np.ndarray, gamma: float
) -> np.ndarray:
    """Eq. 18 for every transition i of linked trajectories: G_i = r_i + γ·G_{successor[i]}, and
    G_i = r_i + γ·bootstrap[i] where successor[i] = −1 (the trajectory's end).

    `order` lists the transitions so that each comes before its successor (the replay's addition order).
    """
    g = np.zeros(len(reward))
    for i in order[::-1].tolist():  # successors first
        nxt = successor[i]
        g[i] = reward[i] + gamma * (g[nxt] if nxt >= 0 else bootstrap[i])
    return g


def frame_sums(rows: np.ndarray, returns: np.ndarray, total_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(visits [F], summed returns [F]) per library frame."""
    rows = np.asarray(rows, int)
    return np.bincount(rows, minlength=total_frames), np.bincount(rows, weights=returns, minlength=total_frames)


class FrameValues:
    """V_t of every library frame (Eq. 19), initialised to zero, and the start weights they give."""

    def __init__(self, total_frames: int, rate: float = 0.5, gamma: float = 0.95, floor: float = 0.01):
        if not 0 < rate <= 1 or not 0 < gamma <= 1:
            raise ValueError(f"need 0 < rate <= 1 and 0 < gamma <= 1, got {rate} and {gamma}")
        self.values = np.zeros(total_frames)
        self.visits = np.zeros(total_frames, np.int64)  # how often each frame was seen, over all refreshes
        self.rate, self.gamma, self.floor = rate, gamma, floor
        self.refreshes = 0

    def update(self, count: np.ndarray, total: np.ndarray) -> np.ndarray:
        """Eq. 19 for every frame seen: `count` [F] visits and `total` [F] summed V* of this refresh
        (`frame_sums`), so a frame seen k times moves toward the mean of its k returns; the frames updated."""
        count, total = np.asarray(count), np.asarray(total, float)
        seen = np.flatnonzero(count)
        target = total[seen] / count[seen]
        self.values[seen] = (1 - self.rate) * self.values[seen] + self.rate * target
        self.visits += count.astype(np.int64)
        self.refreshes += 1
        return seen

    def weights(self) -> np.ndarray:
        """Start weights ∝ 1 / max(floor, V_t)."""
        return balancing_weights(self.values, self.floor)

    def clip_summary(self, library: MotionLibrary) -> dict[str, np.ndarray]:
        """Per clip: the mean value of its frames and its share of the start probability."""
        w = self.weights()
        usable = np.ones(len(w), bool)
        usable[(library.offsets + library.num_frames - 1)[~library.loop & (library.num_frames > 1)]] = False
        w = np.where(usable, w, 0.0)
        clip = np.repeat(np.arange(library.num_clips), library.num_frames)
        value = np.bincount(clip, weights=self.values) / library.num_frames
        share = np.bincount(clip, weights=w) / w.sum()
        return {"value": value, "share": share}

    def state_dict(self) -> dict[str, Any]:
        return {"values": self.values.copy(), "visits": self.visits.copy(), "refreshes": self.refreshes}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.values = np.asarray(state["values"], float).copy()
        self.visits = np.asarray(state["visits"], np.int64).copy()
        self.refreshes = int(state["refreshes"])
