"""The motion library: processed clips, looked up and sampled in batches.

All clips' frames are concatenated into flat arrays, so a lookup of N (clip,
frame) pairs is a few NumPy gathers. Frames past the end of a cyclic clip are
the clip's frames moved by whole cycles (root displacement and heading carried
over); past the end of a one-shot clip they clamp to its last frame.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from workers.body import rotations as rot
from workers.body.character import Character
from workers.body.features import state_features
from workers.motion import clip as clip_mod
from workers.motion.clip import MotionClip, RawClip
from workers.motion.errors import ClipError
from workers.motion.formats import load_raw, resolve
from workers.types import KinState

log = logging.getLogger(__name__)

CACHE_VERSION = "4"  # 2: BVH imports grounded, matched by naming conventions; 3: last frame kept; 4: BVH unit
# from the legs, limb twists from the motion, Rigify names
_FRAME_FIELDS = ("qpos", "qvel", "xpos", "xquat", "lin_vel", "ang_vel")


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME", str(Path.home() / ".cache"))
    return Path(os.environ.get("MOCAP_CACHE_DIR", Path(base) / "mocap-orchestrator" / "motion"))


class MotionLibrary:
    def __init__(self, character: Character, clips: Sequence[MotionClip]):
        if not clips:
            raise ValueError("a motion library needs at least one clip")
        dts = [c.dt for c in clips]
        if max(dts) - min(dts) > 0.05 * min(dts):
            raise ValueError(f"clips sampled at different rates: {sorted({round(d, 3) for d in dts})}")
        self.character = character
        self.clips = list(clips)
        self.names = [c.name for c in clips]
        self.num_frames = np.array([c.num_frames for c in clips])
        self.offsets = np.concatenate(([0], np.cumsum(self.num_frames)[:-1]))
        self.loop = np.array([c.loop for c in clips])
        self.dt = np.array([c.dt for c in clips])
        self.cycle_yaw = np.array([c.cycle_yaw for c in clips])
        self.cycle_shift = np.stack([c.cycle_shift for c in clips])
        for f in _FRAME_FIELDS:
            setattr(self, "_" + f, np.concatenate([getattr(c, f) for c in clips]))
        # s does not change under yaw rotation and horizontal shifts, so one row per
        # stored frame serves every cycle of a looping clip.
        self._features = state_features(KinState(*(getattr(self, "_" + f) for f in _FRAME_FIELDS)))
        # The PD targets that hold each frame's joint rotations (a cycle turns only the root).
        self._pd_targets = character.qpos_to_action(self._qpos).astype(np.float32)
        # Start-state sampling: uniform over usable frames unless weights are set.
        self._frame_weights = np.ones(int(self.num_frames.sum()))

    # Construction ----------------------------------------------------------
    @classmethod
    def load(
        cls,
        character: Character,
        clips: Sequence[str | Path],
        fps: float = 30.0,
        mirror: bool = False,
        cache_dir: str | Path | None = None,
        use_cache: bool = True,
        joint_map: dict[str, str] | None = None,
    ) -> MotionLibrary:
        """Load clips by bundled name or path, resample to fps, optionally add mirrored copies.

        joint_map: for BVH files, source joint name -> our body, added to (and overriding) the
        naming conventions of workers.motion.formats.bvh_names.
        """
        out = []
        for item in clips:
            out.append(load_clip(character, item, fps, False, cache_dir, use_cache, joint_map))
            if mirror:
                out.append(load_clip(character, item, fps, True, cache_dir, use_cache, joint_map))
        return cls(character, out)

    @property
    def num_clips(self) -> int:
        return len(self.clips)

    @property
    def total_frames(self) -> int:
        return int(self.num_frames.sum())

    def clip_id(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no clip {name!r} in the library (have {self.names})") from None

    # Lookup ----------------------------------------------------------------
    def state(self, clip_ids: np.ndarray, frames: np.ndarray) -> KinState:
        """Reference states [N] at integer frames (any non-negative integer) of the given clips."""
        clip_ids = np.asarray(clip_ids, dtype=int)
        rows, cycles = self.rows(clip_ids, np.asarray(frames, dtype=int))
        s = KinState(*(getattr(self, "_" + f)[rows] for f in _FRAME_FIELDS))
        if np.any(cycles):
            yaw, shift = self.cycle_power(clip_ids, cycles)
            s = transform_state(s, yaw, shift)
        return s

    def body_positions(self, clip_ids: np.ndarray, frames: np.ndarray, body: int) -> np.ndarray:
        """World position [N, 3] of one body at the given frames: `state(...).xpos[:, body]`, cheaply."""
        clip_ids = np.asarray(clip_ids, dtype=int)
        rows, cycles = self.rows(clip_ids, np.asarray(frames, dtype=int))
        pos = self._xpos[rows, body]
        if np.any(cycles):
            yaw, shift = self.cycle_power(clip_ids, cycles)
            c, s = np.cos(yaw), np.sin(yaw)
            pos = np.stack((c * pos[:, 0] - s * pos[:, 1], s * pos[:, 0] + c * pos[:, 1], pos[:, 2]), -1) + shift
        return pos

    def features(self, clip_ids: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """The state features s [N, D] of the reference at the given frames (see `state`)."""
        return self._features[self.rows(np.asarray(clip_ids, dtype=int), np.asarray(frames, dtype=int))[0]]

    def pd_targets(self, clip_ids: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """[N, A] float32 PD targets holding the reference's joints at the given frames:
        `character.qpos_to_action(state(...).qpos)`, looked up instead of computed."""
        return self._pd_targets[self.rows(np.asarray(clip_ids, dtype=int), np.asarray(frames, dtype=int))[0]]

    def stored_frames(self) -> tuple[KinState, np.ndarray]:
        """(Every stored frame's state, its s [total_frames, D]), in the flat row order of `rows`: the tables a
        lookup elsewhere (`workers.models.device_features.DeviceReference`) indexes by `rows` and `cycle_power`."""
        return KinState(*(getattr(self, "_" + f) for f in _FRAME_FIELDS)), self._features

    def stored_pd_targets(self) -> np.ndarray:
        """[total_frames, A] float32: `pd_targets`' table, every stored frame's, in the flat row order of `rows`."""
        return self._pd_targets

    def rows(self, clip_ids: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the flat arrays and the number of whole cycles past the clip's end."""
        n = self.num_frames[clip_ids]
        loop = self.loop[clip_ids]
        cycles = np.where(loop, frames // n, 0)
        local = np.where(loop, frames % n, np.minimum(frames, n - 1))
        return self.offsets[clip_ids] + local, cycles

    def cycle_power(self, clip_ids: np.ndarray, cycles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cycle transform applied `cycles` times: yaw c·θ, shift Σ_{i<c} R(iθ) d (closed form)."""
        theta = self.cycle_yaw[clip_ids]
        d = self.cycle_shift[clip_ids][:, :2] @ np.array([1.0, 1j])  # complex xy
        c = cycles.astype(float)
        small = np.abs(theta) < 1e-9
        ratio = np.where(small, c, (1 - np.exp(1j * c * theta)) / np.where(small, 1, 1 - np.exp(1j * theta)))
        z = d * ratio
        shift = np.stack((z.real, z.imag, np.zeros_like(c)), axis=-1)
        return c * theta, shift

    def is_last_frame(self, clip_ids: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """True where a one-shot clip has no frame after `frames`."""
        return ~self.loop[clip_ids] & (frames >= self.num_frames[clip_ids] - 1)

    # Sampling --------------------------------------------------------------
    def set_frame_weights(self, weights: np.ndarray) -> None:
        """Per-frame start weights [total_frames] (e.g. ControlVAE's data balancing)."""
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (self.total_frames,) or (weights < 0).any() or not np.isfinite(weights).all():
            raise ValueError(f"frame weights must be {self.total_frames} finite non-negative numbers")
        self._frame_weights = weights.copy()

    def set_clip_weights(self, weights: Sequence[float]) -> None:
        """Per-clip start weights, spread evenly over each clip's frames."""
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (self.num_clips,) or (weights < 0).any() or weights.sum() <= 0:
            raise ValueError(f"clip weights must be {self.num_clips} non-negative numbers, not all zero")
        self._frame_weights = np.repeat(weights / self.num_frames, self.num_frames)

    def sample_starts(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(clip_ids [n], frames [n]) drawn ∝ the frame weights; never the last frame of a one-shot clip."""
        w = self._frame_weights.copy()
        last = self.offsets + self.num_frames - 1
        w[last[~self.loop & (self.num_frames > 1)]] = 0.0
        if w.sum() <= 0:
            raise ValueError("all start weights are zero")
        rows = rng.choice(len(w), size=n, p=w / w.sum())
        clip_ids = np.searchsorted(self.offsets, rows, side="right") - 1
        return clip_ids, rows - self.offsets[clip_ids]


def balancing_weights(values: np.ndarray, floor: float = 0.01) -> np.ndarray:
    """ControlVAE's data balancing (Eq. 18-20): start weight ∝ 1 / max(floor, V)."""
    return 1.0 / np.maximum(floor, np.asarray(values, dtype=float))


def transform_state(s: KinState, yaw: np.ndarray, shift: np.ndarray) -> KinState:
    """Rotate about z by yaw [N] and translate by shift [N, 3] every world quantity of s."""
    rz_t = rot.yaw_matrix(yaw).transpose(0, 2, 1)  # [N, 3, 3], for row vectors
    qz = rot.from_yaw(yaw)  # [N, 4]
    qpos = clip_mod.transform_qpos(s.qpos, yaw, shift)
    qvel = s.qvel.copy()
    qvel[:, None, :3] = s.qvel[:, None, :3] @ rz_t  # free joint: world linear velocity
    return KinState(
        qpos=qpos,
        qvel=qvel,
        xpos=s.xpos @ rz_t + shift[:, None, :],
        xquat=rot.mul(qz[:, None, :], s.xquat),
        lin_vel=s.lin_vel @ rz_t,
        ang_vel=s.ang_vel @ rz_t,
    )


# ----------------------------------------------------------------------------
# Loading with an NPZ cache
# ----------------------------------------------------------------------------
def load_clip(
    character: Character,
    name_or_path: str | Path,
    fps: float,
    mirror: bool = False,
    cache_dir: str | Path | None = None,
    use_cache: bool = True,
    joint_map: dict[str, str] | None = None,
) -> MotionClip:
    """A processed clip, from the NPZ cache when the source, character, rate and joint map are unchanged."""
    path = resolve(name_or_path)
    mapping = json.dumps({str(k): str(v) for k, v in (joint_map or {}).items()}, sort_keys=True)
    parts = [path.read_bytes(), character.xml_hash.encode(), f"{fps:.6f}|{mirror}|{CACHE_VERSION}".encode()]
    key = hashlib.sha1(b"|".join(parts + ([mapping.encode()] if joint_map else []))).hexdigest()[:16]
    cache = Path(cache_dir) if cache_dir else default_cache_dir()
    cached = cache / f"{Path(str(name_or_path)).stem}-{key}.npz"
    if use_cache and cached.exists():
        try:
            with np.load(cached, allow_pickle=False) as d:
                return MotionClip.from_npz_dict(d)
        except Exception as e:  # a corrupt cache entry is rebuilt, never fatal
            log.warning("ignoring unreadable cache entry %s (%s)", cached, e)
    raw: RawClip = load_raw(character, name_or_path, joint_map=joint_map or None)
    if mirror:
        raw = clip_mod.mirror_raw(character, raw)
    clip = clip_mod.process(character, raw, fps)
    if use_cache:
        try:
            cache.mkdir(parents=True, exist_ok=True)
            tmp = cached.with_suffix(".tmp.npz")
            np.savez_compressed(tmp, **clip.to_npz_dict())
            os.replace(tmp, cached)
        except OSError as e:
            log.warning("could not write the clip cache %s (%s)", cached, e)
    return clip


__all__ = ["MotionLibrary", "ClipError", "balancing_weights", "load_clip", "transform_state"]
