"""Secrets on disk, for the cluster's state dir and a sweep's tracking server: private directories (0700), secret
files (0600), and directories kept outside the state dir, whose place the state dir remembers.

Modes are set whether the file or directory is new or was already there (an older state dir, a copy, a umask of
022): creating with a mode changes nothing on an existing path, so every helper here also chmods.
"""

from __future__ import annotations

import os
import secrets
import tempfile
from collections.abc import Callable
from pathlib import Path

DIR_MODE = 0o700
SECRET_MODE = 0o600


def private_dir(path: Path) -> Path:
    """`path` (and missing parents) as a directory only its owner can enter: mode 0700, new or existing."""
    path.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
    path.chmod(DIR_MODE)
    return path


def write_secret(path: Path, text: str) -> None:
    """Write `text` to `path` with mode 0600, new or existing (never readable by others, not even for a moment)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, SECRET_MODE)
    with os.fdopen(fd, "w") as f:
        os.fchmod(fd, SECRET_MODE)
        f.write(text)


def read_secret(path: Path, make: Callable[[], str] | None = None) -> str:
    """The secret in `path` (its mode set to 0600); when the file is missing, `make()` written there first."""
    if not path.exists():
        if make is None:
            raise FileNotFoundError(path)
        write_secret(path, make())
    path.chmod(SECRET_MODE)
    return path.read_text().strip()


def new_password() -> str:
    """192 random bits, URL-safe (no characters a URI, a shell or an ini file would read specially)."""
    return secrets.token_urlsafe(24)


def kept_dir(state_dir: Path, pointer: str, prefix: str, owner: int | None = None, parent: Path | None = None) -> Path:
    """A directory outside the state dir (under `parent`, default /tmp) that outlives `down`: the one named in
    `<state-dir>/<pointer>` when it is still there, a real directory owned by `owner` (default: this user), else a
    new one recorded there. Its mode is 0700 and `owner` owns it."""
    owner = os.geteuid() if owner is None else owner
    record = state_dir / pointer
    if record.exists():
        previous = Path(record.read_text().strip())
        if previous.is_dir() and not previous.is_symlink() and previous.stat().st_uid == owner:
            previous.chmod(DIR_MODE)
            return previous
    if parent is None and os.path.isdir("/tmp"):
        parent = Path("/tmp")
    new = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))  # mode 0700
    if owner != os.geteuid():
        os.chown(new, owner, -1)
    write_secret(record, f"{new}\n")
    return new
