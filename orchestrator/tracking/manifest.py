"""A run's artifacts by their SHA-256: what a tracker uploaded, so that whoever reuses the run can check them.

The tracker records the digest of every file it submits (`Manifest.add`, at submission, before the file can
change or an owned one is deleted) and forgets a deleted one. When a run ends FINISHED, the manifest is the
run's last artifact, `MANIFEST_FILE`, and the tag `COMPLETE_TAG` (the manifest's own SHA-256) is set after it,
behind every upload still waiting in the tracker's spool: a run without that tag has files missing or is
from before manifests, and is not reused as a stage (`orchestrator.stages`). A reader checks each file it
downloads (`check`). The entries are kept in the run directory as they come (`FILE`), so a resumed run's
manifest still lists what its first process uploaded.

This protects against files that changed or went missing (a stalled upload, a bad disk, a hand edit); it
is not a signature: whoever can write a run's artifacts can write its manifest too (who may be trusted is
`orchestrator.stages`' business).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

MANIFEST_FILE = "artifacts.sha256.json"  # the run's last artifact: {artifact path: sha256}
FILE = "tracking-digests.json"  # in the run directory: the entries so far
COMPLETE_TAG = "artifacts_sha256"  # the manifest's SHA-256, set after the run's last upload


class ManifestError(ValueError):
    """An artifact that does not match its run's manifest; the message names the file."""


def sha256(path: str | Path) -> str:
    """The SHA-256 of a file's contents, in hex."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def text_digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


class Manifest:
    """The digests of a run's artifacts, kept in `<run_dir>/FILE` (continued by a resumed run, else restarted)."""

    def __init__(self, run_dir: Path, resumed: bool):
        self.path = Path(run_dir) / FILE
        self.entries: dict[str, str] = {}
        if resumed and self.path.is_file():
            try:
                self.entries = dict(json.loads(self.path.read_text()))
            except (ValueError, TypeError):  # unreadable: the artifacts of the first process go unlisted
                self.entries = {}
        self._save()

    def add(self, local: Path, artifact_path: str | None) -> None:
        """Record `local` (a file, or every file of a directory) as uploaded under `artifact_path`."""
        prefix = f"{artifact_path.strip('/')}/" if artifact_path else ""
        if local.is_dir():
            for f in sorted(p for p in local.rglob("*") if p.is_file()):
                self.entries[prefix + f.relative_to(local).as_posix()] = sha256(f)
        elif local.is_file():
            self.entries[prefix + local.name] = sha256(local)
        self._save()

    def remove(self, artifact_path: str) -> None:
        """Forget `artifact_path` (a file, or a folder and everything under it)."""
        key = artifact_path.strip("/")
        self.entries = {k: v for k, v in self.entries.items() if k != key and not k.startswith(key + "/")}
        self._save()

    def text(self) -> str:
        return json.dumps(dict(sorted(self.entries.items())), indent=1) + "\n"

    def _save(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.entries))
        os.replace(tmp, self.path)


def parse(text: str, digest: str, where: str) -> dict[str, str]:
    """The entries of a downloaded manifest whose SHA-256 must be `digest` (the run's `COMPLETE_TAG`)."""
    if text_digest(text) != digest:
        raise ManifestError(f"{where}: {MANIFEST_FILE} does not match the run's {COMPLETE_TAG} tag")
    try:
        entries = json.loads(text)
    except ValueError:
        raise ManifestError(f"{where}: {MANIFEST_FILE} is not JSON") from None
    if not isinstance(entries, dict):
        raise ManifestError(f"{where}: {MANIFEST_FILE} is not a mapping of paths to digests")
    return {str(k): str(v) for k, v in entries.items()}


def check(entries: dict[str, str], artifact_path: str, local: Path, where: str) -> None:
    """ManifestError naming the file unless `local` (downloaded from `artifact_path`) is as the manifest says."""
    expected = entries.get(artifact_path.strip("/"))
    if expected is None:
        raise ManifestError(f"{where}: artifact {artifact_path} is not in its {MANIFEST_FILE}")
    if sha256(local) != expected:
        raise ManifestError(
            f"{where}: artifact {artifact_path} does not match its SHA-256 in {MANIFEST_FILE} (changed since the run)"
        )
