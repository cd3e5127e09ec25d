"""A finished stage, read back: where its run is, and its config, checkpoint, metrics and outputs.

A run's upstream stages (`algo.needs`, `orchestrator.stages`) reach its method and components as
`Upstream` objects: small (they pickle into Ray actors), they download the stage's artifacts
themselves, so that a restarted actor, or one on another node, needs nothing from the driver.
Each reader names the stage and the artifact when something is missing or unusable (`StageError`):

- `Upstream.config()`, `.checkpoint()`, `.metrics()`, `.artifact(path)`;
- `expert_weights`: an expert's network (a tracker or amp run's PPO actor, a controlvae run's VAE);
- `load_demos`, `load_manifest`: the demos dataset an `algo=demos` stage wrote;
- `layer_state`: PhysicsVAE's simulation layer, from a world_model stage's checkpoint;
- `existing_run`: a finished run given by its id (`tracking.query.complete_runs` finds them by stage hash).

A stage found by its hash carries its manifest's digest (`manifest_digest`, the run's `artifacts_sha256` tag):
every artifact it downloads is checked against the manifest (`orchestrator.tracking.manifest`), and one that
does not match is a StageError naming the run and the file; `verify` checks what a consumer reads before the
stage is used.
"""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from orchestrator import checkpoint
from orchestrator.compose import find_method, validate
from orchestrator.schema import Config, ConfigError
from orchestrator.tracking import manifest, query
from orchestrator.tracking.uri import redact
from workers.demos import DemoError, DemoSet
from workers.learners.base import Weights

# A need given as an existing run instead of a stage: run:<id> or the bare 32-digit id.
RUN_ID = re.compile(r"(?:run:)?([0-9a-f]{32})")
# The demos stage's artifacts (written by `orchestrator.algos.demos`).
DEMOS_FILE = "demos/demos.npz"
MANIFEST_FILE = "demos/manifest.json"


class StageError(RuntimeError):
    """An upstream stage that cannot be used; the message names the stage and what is wrong."""


@dataclass
class Upstream:
    """A finished stage that a run uses: where it is and how to read its outputs."""

    role: str
    name: str  # the stage's method (algo.name)
    run_id: str
    stage_hash: str
    uri: str
    cache: Path  # its artifacts are downloaded under cache/<run id> (never served to another run)
    reused: bool  # found finished in the store, not run for this one
    lineage: dict[str, str] = field(default_factory=dict)  # "demos.expert" -> run id, for every stage above
    provenance: dict[str, str] = field(default_factory=dict)  # its run's experiment, user and git commit
    manifest_digest: str | None = None  # its manifest's SHA-256: artifacts are checked (None: a run named by id
    # that has no manifest, used unchecked)
    _entries: dict[str, str] | None = field(default=None, repr=False)

    def describe(self) -> str:
        return f"stage {self.role} ({self.name}, run {self.run_id})"

    def artifact(self, path: str) -> Path:
        """The artifact `path` of the stage's run, downloaded; a StageError naming both when it is not there, or
        when the path (a name the store lists) is absolute or climbs out with '..': it would land outside the cache."""
        parts = Path(path).parts
        if not parts or Path(path).is_absolute() or ".." in parts or "\\" in path:
            raise StageError(f"{self.describe()}: artifact path {path!r} is refused (absolute, empty or with '..')")
        local = self._download(path)
        if self.manifest_digest is not None:
            try:
                manifest.check(self.entries(), path, local, self.describe())
            except manifest.ManifestError as e:
                local.unlink(missing_ok=True)  # not served from the cache next time
                raise StageError(str(e)) from None
        return local

    def entries(self) -> dict[str, str]:
        """The stage's manifest {artifact path: sha256}, downloaded once and checked against its digest."""
        if self._entries is None:
            try:
                text = self._download(manifest.MANIFEST_FILE).read_text()
                self._entries = manifest.parse(text, self.manifest_digest or "", self.describe())
            except (manifest.ManifestError, OSError) as e:
                raise StageError(str(e)) from None
        return self._entries

    def verify(self) -> None:
        """Check now what a consumer of the stage reads (its config, newest checkpoint and demos): a StageError
        naming the file at the first that does not match its manifest, or is missing."""
        names = self.entries()
        newest = sorted(n for n in names if re.fullmatch(r"checkpoints/ckpt-\d+\.pt", n))[-1:]
        for name in ["config.json", *newest, *sorted(n for n in names if n.startswith("demos/"))]:
            self.artifact(name)

    def _download(self, path: str) -> Path:
        folder = self.cache / self.run_id
        local = folder / path
        if local.exists():
            return local
        folder.mkdir(parents=True, exist_ok=True)
        try:
            out = query.download_artifact(self.uri, self.run_id, path, folder)
        except Exception as e:
            hint = ""
            if "mlflow-artifacts" in str(e):
                hint = "; its artifacts are served by a tracking server: give that server as tracking.uri"
            raise StageError(
                f"{self.describe()}: artifact {path} is missing or unreadable ({short_error(e)}){hint}"
            ) from None
        if not out.exists():
            raise StageError(f"{self.describe()}: artifact {path} is missing")
        return out

    def config(self) -> Config:
        """The stage's config (`config.json`); a method class it names is imported only if it is one we ship."""
        path = self.artifact("config.json")
        try:
            return validate(json.loads(path.read_text()), shipped_only=True)
        except (json.JSONDecodeError, ConfigError) as e:
            raise StageError(f"{self.describe()}: artifact config.json is unreadable ({short_error(e)})") from None

    def checkpoint(self) -> dict[str, Any]:
        """The stage's last checkpoint (state dicts, loaded with weights_only=True)."""
        try:
            names = query.list_artifacts(self.uri, self.run_id, "checkpoints")
        except Exception as e:
            raise StageError(f"{self.describe()}: cannot list its checkpoints ({short_error(e)})") from None
        names = sorted(n for n in names if re.search(r"ckpt-\d+\.pt$", n))
        if not names:
            raise StageError(f"{self.describe()}: artifact checkpoints/ckpt-*.pt is missing")
        path = self.artifact(names[-1])
        try:
            return checkpoint.load(path)
        except checkpoint.CheckpointError as e:  # truncated, not a weights file, not a dict of states
            raise StageError(f"{self.describe()}: artifact {names[-1]} ({path}): {e.message}") from None

    def metrics(self) -> dict[str, float]:
        return query.run_metrics(self.uri, self.run_id)


def short_error(e: BaseException) -> str:
    """The first line of an error's message (200 characters at most), else its type's name."""
    return str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__


def existing_run(role: str, run_id: str, uri: str, cache: Path) -> Upstream:
    """A run given by its id (`run:<id>`) as the stage `role`: it must be in the store and FINISHED."""
    try:
        status, tags = query.run_status_and_tags(uri, run_id)
    except Exception as e:
        raise StageError(f"stage {role}: run {run_id} is not in {redact(uri)} ({short_error(e)})") from None
    if status != "FINISHED":
        raise StageError(f"stage {role}: run {run_id} is {status}, not FINISHED")
    if not tags.get(manifest.COMPLETE_TAG):
        print(
            f"stage {role}: run {run_id} has no {manifest.MANIFEST_FILE} (from before manifests, or its uploads "
            "did not all land): its artifacts are used unchecked",
            file=sys.stderr,
        )
    lineage = {
        k.removeprefix("upstream."): v
        for k, v in tags.items()
        if k.startswith("upstream.") and k.rpartition(".")[2] not in ("reused", *query.PROVENANCE)
    }
    name = tags.get("algo", "?")
    origin = provenance(role, uri, run_id)
    digest = tags.get(manifest.COMPLETE_TAG) or None
    return Upstream(role, name, run_id, tags.get("stage_hash", run_id), uri, cache, True, lineage, origin, digest)


def provenance(role: str, uri: str, run_id: str) -> dict[str, str]:
    """Where stage `role`'s run came from (`tracking.query.run_provenance`); a StageError if the store cannot say."""
    try:
        return query.run_provenance(uri, run_id)
    except Exception as e:
        raise StageError(f"stage {role}: cannot read run {run_id} in {redact(uri)} ({short_error(e)})") from None


def manifest_digest(role: str, uri: str, run_id: str) -> str | None:
    """Run `run_id`'s manifest digest (its `artifacts_sha256` tag); None while its uploads have not all landed."""
    try:
        return query.run_status_and_tags(uri, run_id)[1].get(manifest.COMPLETE_TAG) or None
    except Exception as e:
        raise StageError(f"stage {role}: cannot read run {run_id} in {redact(uri)} ({short_error(e)})") from None


def expert_weights(up: Upstream) -> Weights:
    """The expert network of an upstream run, as the weights an `ExpertPolicy` loads: a run of a method whose
    class says it can be one (`Method.expert`: PPO's actor of a tracker or amp run, or a controlvae run's VAE)."""
    cfg = up.config()
    cls = find_method(cfg.algo._target_)
    state = up.checkpoint()
    version = int(state.get("loop", {}).get("iteration", 0))
    if cls.expert == "ppo" and "ppo" in state:
        payload = {
            "kind": "ppo",
            "config": cfg.algo.ppo,
            "observation": cls.observation_of(cfg),
            "residual": cls.residual,
            "module": state["ppo"]["module"],
        }
    elif cls.expert == "vae" and "vae" in state:
        payload = {"kind": "vae", "config": cfg.algo.vae, "module": state["vae"]["learner"]["module"]}
    else:
        raise StageError(f"{up.describe()}: a {cfg.algo.name} run is not an expert (tracker, amp or controlvae)")
    return Weights(version, payload)


def layer_state(up: Upstream) -> dict[str, Any]:
    """The frozen simulation layer's weights from a world_model stage's last checkpoint."""
    state = up.checkpoint()
    if "world_model" not in state:
        raise StageError(f"{up.describe()}: its checkpoint has no world_model state")
    return state["world_model"]["learner"]["module"]


def load_manifest(up: Upstream) -> dict[str, Any]:
    try:
        return json.loads(up.artifact(MANIFEST_FILE).read_text())
    except (json.JSONDecodeError, OSError) as e:
        raise StageError(f"{up.describe()}: artifact {MANIFEST_FILE} is unreadable ({e})") from None


def load_demos(up: Upstream) -> tuple[DemoSet, dict[str, Any]]:
    """The dataset and manifest of an upstream demos stage; a StageError naming the artifact if unusable."""
    manifest = load_manifest(up)
    try:
        demos = DemoSet.load(up.artifact(DEMOS_FILE))
    except DemoError as e:
        raise StageError(f"{up.describe()}: artifact {DEMOS_FILE}: {e}") from None
    return demos, manifest
