"""Where a result came from: the code that computed it and the contents of the files it read.

A stage is reused by its hash (`orchestrator.stages`), so the hash must change whenever what decides
the result does, including the inputs a config names only by path:

- `inputs_digest(cfg)`: SHA-256 of the character file and of every clip file, by content (a clip
  edited in place, or another file at the same path, is a different stage);
- `code_version(how)`: a digest of the source files that compute a stage's result ("source", the default:
  `SOURCE`, so a change to a loss, a learner or a method retrains the stages it feeds, and a change elsewhere
  does not), the package's version ("version": what we bump by hand, which went unbumped for 39 commits), or
  the git commit of the checkout ("commit": every commit retrains every stage); see the README's section on
  stages;
- `git_commit()`: the checkout's commit, recorded as a tag on every run.
"""

from __future__ import annotations

import hashlib
import subprocess
from functools import lru_cache
from importlib import metadata
from pathlib import Path

from orchestrator.tracking.manifest import sha256
from workers.body.character import HUMANOID_XML
from workers.motion.formats import resolve

PACKAGE = "mocap-orchestrator"
CODE_VERSIONS = ("source", "version", "commit")
ROOT = Path(__file__).resolve().parents[1]  # the folder holding workers/ and orchestrator/
# The source files whose code decides what a stage computes: the whole data plane, and the control plane's
# methods, components, loop and the readers of upstream stages. Not in it: tracking, sweeps and their reports,
# benchmarks, the cluster commands, the console.
SOURCE = (
    "workers", "orchestrator/algos", "orchestrator/components", "orchestrator/evaluation",
    "orchestrator/trainer.py", "orchestrator/world.py", "orchestrator/upstream.py", "orchestrator/checkpoint.py",
)  # fmt: skip


def git_commit() -> str:
    """The commit of the checkout this code runs from, "unknown" outside one."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            cwd=Path(__file__).resolve().parent,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def code_version(how: str = "source") -> str:
    """What of the code a stage hash covers: the digest of its source files, the package's version, or the
    git commit."""
    if how == "source":
        return f"source {source_digest(ROOT)}"
    if how == "commit":
        return f"commit {git_commit()}"
    try:
        return f"{PACKAGE} {metadata.version(PACKAGE)}"
    except metadata.PackageNotFoundError:
        return f"{PACKAGE} unknown"


def source_digest(root: Path) -> str:
    """SHA-256 over the `SOURCE` Python files under `root`, each by its path relative to `root` and its bytes."""
    files: list[Path] = []
    for name in SOURCE:
        path = root / name
        files.extend(sorted(path.rglob("*.py")) if path.is_dir() else [path] if path.is_file() else [])
    h = hashlib.sha256()
    for path in files:
        h.update(f"{path.relative_to(root).as_posix()}\0{file_digest(path)}\0".encode())
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    """SHA-256 of the file's bytes (remembered while its size and modification time stay the same)."""
    p = Path(path).resolve()
    st = p.stat()
    return _digest(str(p), st.st_size, st.st_mtime_ns)


@lru_cache(maxsize=1024)
def _digest(path: str, size: int, mtime_ns: int) -> str:
    return sha256(path)


def inputs_digest(character_xml: str | None, clips: list[str]) -> dict[str, object]:
    """The contents of what a run reads by path: the character file and each clip, as SHA-256 digests."""
    return {
        "character": file_digest(character_xml or HUMANOID_XML),
        "clips": [file_digest(resolve(c)) for c in clips],
    }
