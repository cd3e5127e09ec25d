"""Checkpoints: one file per save, state dicts only, loaded with `weights_only=True`.

NumPy arrays (replay contents, RNG states) are stored as tensors under a marker
so that the safe unpickler can read them back. A file that cannot be used (truncated,
not a weights file, written for networks of other sizes) is a `CheckpointError` naming
it and what is wrong; it is not deleted for that (only `prune` deletes, the oldest first), and a
resume goes on to the one before it (`newest_first`). Each checkpoint has its SHA-256 beside it
(`ckpt-N.pt.sha256`, in `sha256sum`'s format) and `load` checks it, so a file changed after its save (zeroed
pages, a bad disk) is refused like a truncated one; a checkpoint from before digests (no `.sha256`) loads
unchecked. A save is durable once it returns (the file and its directory
are fsynced) and leaves nothing behind if interrupted; `prune` keeps the newest few. The replay buffers,
most of a checkpoint's size (ControlVAE's default 50,000 transitions: 87 MB, against 13 MB for its
networks and optimizers), are saved beside it (`replay-N.pt`, with its digest) and kept for the newest
only, unless `algo.loop.replay_keep` says more; a resume from an older checkpoint refills them. Beside the
checkpoints, a run directory holds `RUN_FILE`, the id of the MLflow run that a resume reopens,
and `LOCK_FILE`, locked by the command that runs in it (`lock_run_dir`).
"""

from __future__ import annotations

import errno
import fcntl
import os
import pickle
import re
import tempfile
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch

from orchestrator.tracking.manifest import sha256

RUN_FILE = "run.json"  # in the run directory: {"run_id": <the MLflow run a resume continues>}
LOCK_FILE = "run.lock"  # in the run directory: locked (flock) while a command runs in it

REPLAY_STEM = "replay"  # replay-N.pt: the replay buffers saved with ckpt-N.pt (`replay_path`)
DIGEST_SUFFIX = ".sha256"  # ckpt-N.pt.sha256 beside ckpt-N.pt: "<hex>  ckpt-N.pt"
_NUMPY = "__numpy__"
# What every checkpoint the trainer writes holds besides its components' states (orchestrator.trainer).
TRAINER_KEYS = ("loop", "method", "workers")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the file and what is wrong."""

    def __init__(self, path: object, message: str):
        self.path = str(path)
        self.message = message
        super().__init__(f"{self.path}: {message}")


# What a disk that filled up or became read-only under a run raises (the quota's too).
DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


@dataclass
class LoopState:
    """The loop's counters, which a checkpoint saves under "loop" and restores (the method's own are in its state
    dict)."""

    iteration: int = 0
    samples: int = 0  # environment transitions collected (the metrics' step)
    # The untrained policy's evaluation (`eval.at_start`): the closing summary's baseline.
    baseline: dict[str, float] = field(default_factory=dict)


class DiskError(RuntimeError):
    """A run stopped by its disk (`DISK_ERRORS`); the message names the file, what stays and how to go on."""


class RunDirBusy(RuntimeError):
    """Another command holds the run directory's lock; the message names the directory."""


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


def save(directory: str | Path, iteration: int, state: dict[str, Any], stem: str = "ckpt") -> Path:
    """Write `<stem>-<iteration>.pt` atomically and durably: written to `<name>.tmp`, fsynced, its digest written
    beside it (`digest_path`), renamed over `<stem>-<iteration>.pt` and the directory fsynced, so a crash leaves the
    previous checkpoints intact and a save that returned survives a power cut. Interrupted (Ctrl-C, a full disk)
    before the rename, it deletes the `.tmp` files. `stem="replay"`: the replay buffers saved beside a checkpoint."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{stem}-{iteration:07d}.pt"
    tmp = path.with_suffix(".tmp")
    digest, digest_tmp = digest_path(path), directory / f"{path.name}{DIGEST_SUFFIX}.tmp"
    try:
        with open(tmp, "wb") as f:
            writer = _Writer(f)
            try:
                torch.save(_encode(state), writer)
            except RuntimeError:
                if writer.error is None:
                    raise
                raise writer.error from None  # torch's writer reports a failed write ("unexpected pos ...")
            f.flush()
            os.fsync(f.fileno())
        digest_tmp.write_text(f"{sha256(tmp)}  {path.name}\n")
        os.replace(digest_tmp, digest)
        os.replace(tmp, path)
    except OSError as e:  # a full disk, a read-only one: said of the file being written
        tmp.unlink(missing_ok=True)
        digest_tmp.unlink(missing_ok=True)
        raise OSError(e.errno, e.strerror, str(tmp)) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        digest_tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(directory)
    return path


class _Writer:
    """The file torch.save writes to, keeping what interrupted a write (an OSError, a KeyboardInterrupt): torch's
    zip writer turns it into a RuntimeError that does not say why."""

    def __init__(self, f: Any):
        self.f, self.error = f, None

    def write(self, data: Any) -> int:
        try:
            return self.f.write(data)
        except BaseException as e:  # a full disk, or Ctrl-C in the middle of a write: re-raised as it was
            self.error = e
            raise

    def flush(self) -> None:
        self.f.flush()


def digest_path(path: str | Path) -> Path:
    """Where checkpoint `path`'s SHA-256 is kept: `<name>.sha256` beside it."""
    path = Path(path)
    return path.with_name(path.name + DIGEST_SUFFIX)


def _fsync_dir(directory: Path) -> None:
    """Make a rename in `directory` durable (POSIX: the entry lives in the directory, not in the file)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def newest_first(directory: str | Path) -> list[Path]:
    """The checkpoints in `directory`, newest (highest iteration) first."""
    return sorted(Path(directory).glob("ckpt-*.pt"), reverse=True)


def latest(directory: str | Path) -> Path | None:
    paths = newest_first(directory)
    return paths[0] if paths else None


def replay_path(path: str | Path) -> Path:
    """Where the replay buffers saved with checkpoint `path` are: `replay-N.pt` beside `ckpt-N.pt`."""
    path = Path(path)
    return path.with_name(REPLAY_STEM + path.name.removeprefix("ckpt"))


def prune(
    directory: str | Path, keep: int, forget: Callable[[Path], None] | None = None, replay_keep: int = 1
) -> list[Path]:
    """Delete all but the `keep` newest checkpoints in `directory`, the replay buffers of all but the `replay_keep`
    newest (and any without their checkpoint), and any `.tmp` left by a save that a crash cut short; the
    checkpoints deleted. `forget(path)` is called before each is deleted (to delete its copy in the store first:
    cut short between the two, the file is still here, and the next prune does both). Only for the command that
    holds the run directory's lock."""
    directory = Path(directory)
    for tmp in [*directory.glob("ckpt-*.tmp"), *directory.glob(f"{REPLAY_STEM}-*.tmp")]:
        tmp.unlink(missing_ok=True)
    paths = newest_first(directory)
    kept_replay = {replay_path(p) for p in paths[: min(keep, replay_keep)]}
    for replay in directory.glob(f"{REPLAY_STEM}-*.pt"):
        if replay not in kept_replay:
            replay.unlink(missing_ok=True)
            digest_path(replay).unlink(missing_ok=True)
    old = paths[keep:]
    for path in old:
        if forget is not None:
            forget(path)
        path.unlink(missing_ok=True)
        digest_path(path).unlink(missing_ok=True)
    return old


def unwritable(directory: str | Path) -> str | None:
    """Why files cannot be written into `directory` (made if missing), e.g. "Read-only file system"; None when
    they can. Tried for real, with a file made and removed in its nearest existing folder (permission bits say
    nothing to root, nor of a read-only mount)."""
    folder = Path(directory).absolute()
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        return f"{folder} is not a directory"
    try:
        fd, name = tempfile.mkstemp(prefix=".write-test-", dir=folder)
        os.close(fd)
        os.unlink(name)
    except OSError as e:
        return e.strerror or type(e).__name__
    return None


def lock_run_dir(run_dir: str | Path) -> TextIO:
    """Lock `run_dir` for this process (an exclusive `flock` on its `LOCK_FILE`, released when the process
    ends, however it ends); the open lock file, to keep open while the run goes on. RunDirBusy naming
    the directory if another command holds it."""
    path = Path(run_dir) / LOCK_FILE
    f = open(path, "a+")  # noqa: SIM115 - held open for the whole run
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        raise RunDirBusy(
            f"run_dir={run_dir}: another command is running in this directory (it holds {LOCK_FILE}); "
            "wait for it to end, or give another run_dir"
        ) from None
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f


def load(path: str | Path) -> dict[str, Any]:
    """The state dict saved in `path`; CheckpointError if it is missing, does not match the digest beside it,
    is truncated, not a weights file, holds more than tensors and plain containers (refused by
    `weights_only=True`), or is not a dict."""
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
    check_digest(path)  # after the load's own checks, which say more of a file that is truncated or not ours
    return _decode(state)


def check_digest(path: Path) -> None:
    """CheckpointError unless `path`'s contents have the SHA-256 written beside it at its save (none there: a
    checkpoint from before digests, not checked)."""
    digest = digest_path(path)
    if not digest.is_file():
        return
    expected = digest.read_text().split()[:1]
    if expected != [sha256(path)]:
        raise CheckpointError(
            path, f"corrupt: its contents do not match the SHA-256 in {digest.name} (changed since it was saved)"
        )


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
    """CheckpointError unless `state` is a trainer's checkpoint with a state for each of `components` (those
    whose states it holds: not the replay buffers, which are saved beside it)."""
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
