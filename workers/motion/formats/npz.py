"""Our compact clip format: a NumPy .npz of generalised coordinates.

Keys: `qpos` [T, nq] (z-up, our character's coordinates), `fps` (scalar),
`loop` (bool), `joint_names` (the character's joint order, checked on load).
The processed-clip cache (workers.motion.library) uses the same container with
the full kinematics added.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from workers.body.character import Character
from workers.motion.clip import RawClip
from workers.motion.errors import ClipError


def load(character: Character, path: str | Path, name: str | None = None) -> RawClip:
    path = Path(path)
    if not zipfile.is_zipfile(path):  # np.load would try it as a pickle, and say so
        raise ClipError(path, "not a readable .npz (not a zip archive: truncated, or another kind of file)")
    try:
        with np.load(path, allow_pickle=False) as d:
            missing = [k for k in ("qpos", "fps") if k not in d]
            if missing:
                raise ClipError(path, f"missing key(s) {missing}")
            qpos, fps = np.asarray(d["qpos"], float), float(d["fps"])
            loop = bool(d["loop"]) if "loop" in d else False
            names = [str(x) for x in d["joint_names"]] if "joint_names" in d else None
    except (zipfile.BadZipFile, ValueError, OSError) as e:
        if isinstance(e, ClipError):
            raise
        raise ClipError(path, f"not a readable .npz ({e})") from None
    if names is not None and names != character.joint_names:
        raise ClipError(path, f"joint order {names} does not match the character's {character.joint_names}")
    if fps <= 0:
        raise ClipError(path, f"fps must be positive, got {fps}")
    if qpos.ndim != 2 or qpos.shape[0] == 0:
        raise ClipError(path, "no frames")
    times = np.arange(qpos.shape[0]) / fps
    return RawClip(name=name or path.stem, qpos=qpos, times=times, loop=loop, source=str(path))


def save(character: Character, raw: RawClip, path: str | Path, fps: float | None = None) -> None:
    fps = fps or 1.0 / float(np.mean(np.diff(raw.times)))
    np.savez_compressed(path, qpos=raw.qpos, fps=fps, loop=raw.loop, joint_names=np.array(character.joint_names))
