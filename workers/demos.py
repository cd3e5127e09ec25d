"""Expert demonstrations as a dataset: noisy expert rollouts of every clip (PhysicsVAE Sec. 5.1.1).

A `DemoSet` holds E episodes stored back to back, each as its L_e + 1 body states
and the L_e actions between them:

    states  [S, B, 13]  body states, S = Σ (L_e + 1)
    actions [S, A]      the PD targets applied in each state (zero on an episode's last state)
    clip    [S]         the clip tracked, frame [S] the reference frame of each state
    episode [S]         the episode of each state
    done    [S]         true on each episode's last state (no action follows it)
    episode_clip, episode_rollout, episode_length, episode_fell, episode_tracking_error  [E]

Windows of T transitions never cross an episode's end. Episodes are split by their
rollout index: the last `holdout` rollouts of every clip are held out of training.
Stored as one `.npz`; a file that does not load, or lacks an array, is refused with
its name and the array.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np


class DemoError(ValueError):
    """A demos file that cannot be used; the message names the file and what is wrong."""


@dataclass
class DemoSet:
    states: np.ndarray
    actions: np.ndarray
    clip: np.ndarray
    frame: np.ndarray
    episode: np.ndarray
    done: np.ndarray
    episode_clip: np.ndarray
    episode_rollout: np.ndarray
    episode_length: np.ndarray
    episode_fell: np.ndarray
    episode_tracking_error: np.ndarray

    @classmethod
    def from_episodes(cls, episodes: list[dict[str, np.ndarray]]) -> DemoSet:
        """Episodes of {"states" [L+1, B, 13], "actions" [L, A], "clip", "rollout", "fell", "tracking_error"}."""
        parts: dict[str, list] = {k: [] for k in ("states", "actions", "clip", "frame", "episode", "done")}
        for e, ep in enumerate(episodes):
            n = len(ep["states"])
            acts = np.zeros((n, ep["actions"].shape[-1]), np.float32)
            acts[: n - 1] = ep["actions"]
            done = np.zeros(n, bool)
            done[-1] = True
            parts["states"].append(ep["states"].astype(np.float32))
            parts["actions"].append(acts)
            parts["clip"].append(np.full(n, ep["clip"], np.int64))
            parts["frame"].append(np.arange(n, dtype=np.int64))
            parts["episode"].append(np.full(n, e, np.int64))
            parts["done"].append(done)
        arrays = {k: np.concatenate(v) for k, v in parts.items()}
        return cls(
            **arrays,
            episode_clip=np.array([ep["clip"] for ep in episodes], np.int64),
            episode_rollout=np.array([ep["rollout"] for ep in episodes], np.int64),
            episode_length=np.array([len(ep["actions"]) for ep in episodes], np.int64),
            episode_fell=np.array([ep["fell"] for ep in episodes], bool),
            episode_tracking_error=np.array([ep["tracking_error"] for ep in episodes], np.float64),
        )

    # Files -------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **{f.name: getattr(self, f.name) for f in fields(self)})
        return path

    @classmethod
    def load(cls, path: str | Path) -> DemoSet:
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [f.name for f in fields(cls) if f.name not in z.files]
                if missing:
                    raise DemoError(f"{path}: no array {missing[0]!r}; not a demos file")
                out = cls(**{f.name: z[f.name] for f in fields(cls)})
        except DemoError:
            raise
        except Exception as e:
            raise DemoError(f"{path}: unreadable demos file ({type(e).__name__}: {e})") from None
        out.check(path)
        return out

    def check(self, path: str | Path = "demos") -> None:
        s = len(self.states)
        for f in ("actions", "clip", "frame", "episode", "done"):
            if len(getattr(self, f)) != s:
                raise DemoError(f"{path}: {f} has {len(getattr(self, f))} rows, states {s}")
        if int(self.episode_length.sum()) + len(self.episode_length) != s:
            raise DemoError(f"{path}: episode lengths do not add up to the {s} states")
        if not np.isfinite(self.states).all() or not np.isfinite(self.actions).all():
            bad = int(np.flatnonzero(~np.isfinite(self.states).reshape(s, -1).all(1))[:1].sum())
            raise DemoError(f"{path}: non-finite values (first at row {bad})")

    # Sizes and splits --------------------------------------------------------
    @property
    def num_episodes(self) -> int:
        return len(self.episode_length)

    @property
    def num_transitions(self) -> int:
        return int(self.episode_length.sum())

    def episodes_of(self, held_out: bool, holdout: int) -> np.ndarray:
        """Episode ids of the training split (False) or the held-out split (True)."""
        per_clip = np.array([self.episode_rollout[self.episode_clip == c].max() + 1 for c in self.episode_clip])
        out = self.episode_rollout >= per_clip - holdout
        if holdout >= per_clip.min():  # nothing would be left to train on: train on everything
            out = np.zeros_like(out) if not held_out else out
        return np.flatnonzero(out == held_out)

    def window_starts(self, length: int, episodes: np.ndarray | None = None) -> np.ndarray:
        """Rows i where states i..i+length lie in one episode (of `episodes`, if given)."""
        rows = np.arange(len(self.states))
        ok = np.ones(len(rows), bool)
        for k in range(length):  # no end within the window's first `length` states
            ok &= ~np.roll(self.done, -k)
        ok[len(rows) - length :] = False
        if episodes is not None:
            ok &= np.isin(self.episode, episodes)
        return rows[ok]

    def windows(self, starts: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray]:
        """(states [N, length+1, B, 13], actions [N, length, A]) of the windows at `starts`."""
        idx = starts[:, None] + np.arange(length + 1)
        return self.states[idx], self.actions[idx[:, :-1]]
