"""Checkpoints: one file per save, state dicts only, loaded with `weights_only=True`.

NumPy arrays (replay contents, RNG states) are stored as tensors under a marker
so that the safe unpickler can read them back. A file that cannot be used (truncated,
not a weights file, written for networks of other sizes) is a `CheckpointError` naming
it and what is wrong; it is never deleted or overwritten here. Beside the checkpoints, a run
directory holds `RUN_FILE`, the id of the MLflow run that a resume reopens.
"""

from __future__ import annotations

import os
import pickle
import re
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

RUN_FILE = "run.json"  # in the run directory: {"run_id": <the MLflow run a resume continues>}

_NUMPY = "__numpy__"
# What every checkpoint the trainer writes holds besides its components' states (orchestrator.trainer).
TRAINER_KEYS = ("loop", "method", "workers")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the file and what is wrong."""

    def __init__(self, path: object, message: str):
        self.path = str(path)
        self.message = message
        super().__init__(f"{self.path}: {message}")


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
    """The state dict saved in `path`; CheckpointError if it is missing, truncated, not a weights file,
    holds more than tensors and plain containers (refused by `weights_only=True`), or is not a dict."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "is a directory, not a checkpoint" if path.is_dir() else "no such file")
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols on the way to refusing a file
            warnings.simplefilter("ignore")
            state = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as e:
        raise CheckpointError(path, _unreadable(path, e)) from None
    if not isinstance(state, dict):
        raise CheckpointError(path, f"not a checkpoint (it holds a {type(state).__name__}, not a dict of states)")
    return _decode(state)


def _unreadable(path: Path, e: Exception) -> str:
    """What is wrong with a file that torch.load refused. torch.save writes a zip archive."""
    with open(path, "rb") as f:
        head = f.read(4)
    if head != b"PK\x03\x04":
        return "not a PyTorch weights file (torch.save writes a zip archive; this is not one)"
    if not zipfile.is_zipfile(path):
        return f"truncated or corrupt (an incomplete zip archive of {path.stat().st_size} bytes)"
    if isinstance(e, pickle.UnpicklingError) and "weights only" in str(e).lower():
        return "holds Python objects besides tensors (refused: checkpoints are loaded with weights_only=True)"
    return f"not a PyTorch weights file (a zip archive that torch.load cannot read: {_one_line(e)})"


def check_layout(path: str | Path, state: dict[str, Any], components: list[str]) -> None:
    """CheckpointError unless `state` is a trainer's checkpoint with a state for each of `components`."""
    missing = [k for k in (*TRAINER_KEYS, *components) if k not in state]
    if missing:
        raise CheckpointError(
            path, f"has no state for {', '.join(missing)} (a checkpoint of another method, or not of this service)"
        )


def check_restore(path: str | Path, state: dict[str, Any], targets: dict[str, Any]) -> None:
    """Load `state[key]` into each of `targets` (objects with `load_state_dict`, built for this config):
    CheckpointError naming the key, and for a size mismatch the tensor and both shapes, if one does not fit."""
    for key, target in targets.items():
        if key not in state:
            raise CheckpointError(path, f"has no state for {key} (a checkpoint of another method?)")
        try:
            target.load_state_dict(state[key])
        except Exception as e:
            raise CheckpointError(path, f"{key}: {load_error(e)}") from None


_SIZE = re.compile(
    r"size mismatch for (\S+): copying a param with shape torch\.Size\((\[.*?\])\) from checkpoint, "
    r"the shape in current model is torch\.Size\((\[.*?\])\)"
)


def load_error(e: BaseException) -> str:
    """torch's `load_state_dict` error on one line: the first size mismatch as `name: [file] in the
    checkpoint, [config] in this config's network`, or the first missing or unexpected keys."""
    text = str(e)
    m = _SIZE.search(text)
    if m:
        name, saved, wanted = m.groups()
        return f"size mismatch for {name}: {saved} in the checkpoint, {wanted} in this config's network"
    for line in text.splitlines():
        if line.strip().startswith(("Missing key(s)", "Unexpected key(s)")):
            return _one_line(line) + " (a network of another architecture)"
    return _one_line(e)


def _one_line(e: BaseException | str) -> str:
    text = " ".join(str(e).split())
    return text[:200] + ("..." if len(text) > 200 else "") if text else type(e).__name__
