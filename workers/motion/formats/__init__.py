"""Clip file formats and where the bundled clips live.

`load_raw(character, name_or_path)` accepts a bundled clip name
(`humanoid3d_walk`, `walker/turn_left0`) or a path to a `.txt`/`.json`
(DeepMimic), `.bvh` or `.npz` file.
"""

from __future__ import annotations

import os
from pathlib import Path

from workers.body.character import Character
from workers.motion.clip import RawClip
from workers.motion.errors import ClipError

MOTION_DIR_ENV = "MOCAP_MOTION_DIR"


def bundled_motion_dir() -> Path:
    """The DeepMimic clips shipped inside the `pybullet` package, or the folder `MOCAP_MOTION_DIR` names: a copy
    of that package's `data/motions`, for a machine without pybullet (scripts/device-warp.sh carries one to the
    GPU machine)."""
    override = os.environ.get(MOTION_DIR_ENV)
    if override:
        if not Path(override).is_dir():
            raise ClipError(override, f"{MOTION_DIR_ENV} names no folder (a copy of pybullet_data's data/motions)")
        return Path(override)
    try:
        import pybullet_data
    except ImportError as e:  # pragma: no cover - pybullet is a dependency
        raise ClipError("pybullet_data", "the bundled clips need the `pybullet` package") from e
    return Path(pybullet_data.getDataPath()) / "data" / "motions"


def bundled_clip_names() -> list[str]:
    """Every bundled humanoid clip: `humanoid3d_*` and `walker/*`."""
    root = bundled_motion_dir()
    names = [p.stem for p in sorted(root.glob("humanoid3d_*.txt"))]
    names += [f"walker/{p.stem}" for p in sorted((root / "walker").glob("*.txt"))]
    return names


def resolve(name_or_path: str | Path) -> Path:
    """A path for a bundled clip name or an existing file; ClipError otherwise (a directory too)."""
    p = Path(name_or_path)
    if p.is_dir():
        raise ClipError(name_or_path, "is a directory, not a clip file (.txt/.json, .bvh or .npz)")
    if p.suffix and p.exists():
        return p
    candidate = bundled_motion_dir() / f"{name_or_path}.txt"
    if candidate.exists():
        return candidate
    if p.exists():
        return p
    raise ClipError(
        name_or_path,
        "no such file or bundled clip (bundled: " + ", ".join(bundled_clip_names()) + ")",
    )


def load_raw(character: Character, name_or_path: str | Path, joint_map: dict[str, str] | None = None) -> RawClip:
    """A clip as read from its file. joint_map: BVH source joint name -> our body (see formats.bvh)."""
    path = resolve(name_or_path)
    bundled = not Path(name_or_path).suffix
    name = str(name_or_path) if bundled else path.stem
    suffix = path.suffix.lower()
    if suffix in (".txt", ".json"):
        from workers.motion.formats import deepmimic

        return deepmimic.load(character, path, name)
    if suffix == ".npz":
        from workers.motion.formats import npz

        return npz.load(character, path, name)
    if suffix == ".bvh":
        from workers.motion.formats import bvh

        return bvh.load(character, path, name, joint_map=joint_map)
    raise ClipError(path, f"unknown clip format {suffix!r} (expected .txt/.json, .bvh or .npz)")
