"""Checkpoints: one file per save, state dicts only, loaded with `weights_only=True`.

NumPy arrays (replay contents, RNG states) are stored as tensors under a marker
so that the safe unpickler can read them back.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

_NUMPY = "__numpy__"


def _encode(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        # Arrays from Ray's object store are read-only; torch wants writable memory.
        x = np.ascontiguousarray(x) if x.flags.writeable else np.array(x, order="C")
        return {_NUMPY: torch.from_numpy(x)}
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, dict):
        return {k: _encode(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_encode(v) for v in x)
    return x


def _decode(x: Any) -> Any:
    if isinstance(x, dict):
        if set(x) == {_NUMPY}:
            return x[_NUMPY].numpy()
        return {k: _decode(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_decode(v) for v in x)
    return x


def save(directory: str | Path, iteration: int, state: dict[str, Any]) -> Path:
    """Write `ckpt-<iteration>.pt` atomically (a crash mid-write leaves the previous one intact)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"ckpt-{iteration:07d}.pt"
    tmp = path.with_suffix(".tmp")
    torch.save(_encode(state), tmp)
    os.replace(tmp, path)
    return path


def latest(directory: str | Path) -> Path | None:
    paths = sorted(Path(directory).glob("ckpt-*.pt"))
    return paths[-1] if paths else None


def load(path: str | Path) -> dict[str, Any]:
    return _decode(torch.load(path, weights_only=True))
