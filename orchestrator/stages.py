"""Stages: runs of methods that feed each other through MLflow artifacts, reused when identical.

A method names the stages it needs in `algo.needs`, role → spec (conf/algo/*.yaml):

    needs: {demos: demos, world_model: world_model}

A spec is either a stage, "<algo> [key=value ...]", composed from conf/ like a run of
its own (`algo=<algo>` at this run's scale, its `algo_scale`, seed 0 unless the spec
says otherwise) and sharing this run's character, motion, runtime and evaluation; or
an existing run, `run:<id>` (or the bare 32-digit id), which must have FINISHED.

Every run carries the tag `stage_hash`: a hash of the resolved config that decides its
result, its upstream stages' hashes in place of their specs (so a changed upstream stage
invalidates everything below it), and nothing that does not change the result
(`run_dir`, `progress`, `tracking`, `preset`, how the runtime is hosted). Resolving a
need looks for a FINISHED run with that hash in the same store, in any experiment: found,
it is reused and its artifacts downloaded; not found (or only FAILED, or unfinished), the
stage runs now, in this process, into the same store. A sweep resolves its points' needs
once, before the points (`orchestrator.sweep`), so they all find the same stages.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

from orchestrator import checkpoint
from orchestrator.schema import Config, ConfigError, validate

if TYPE_CHECKING:
    from mlflow.tracking import MlflowClient

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
RUN_ID = re.compile(r"(?:run:)?([0-9a-f]{32})")
# Keys that do not change what a run produces; runtime keeps only what changes the samples.
NOT_RESULT = ("run_dir", "progress", "tracking", "resume", "preset", "sweep_seeds", "scale_name", "stage_overrides")
RUNTIME_RESULT = ("rollout_workers", "envs_per_worker")
# What an upstream stage shares with the run that needs it.
SHARED = ("character", "motion", "runtime", "eval", "tracking", "progress", "preset", "scale_name", "stage_overrides")
SECTIONS_SHARED = ("character", "motion", "runtime", "eval", "tracking")


class StageError(RuntimeError):
    """An upstream stage that cannot be used; the message names the stage and what is wrong."""


def config_hash(cfg: Config, upstream: dict[str, str] | None = None) -> str:
    """The hash of what decides `cfg`'s result; `upstream` maps each need's role to its stage hash."""
    d: dict[str, Any] = asdict(cfg)
    for key in NOT_RESULT:
        d.pop(key, None)
    d["runtime"] = {k: d["runtime"][k] for k in RUNTIME_RESULT}
    # Sections the method does not use are None: left out, so that a new section elsewhere changes no hash.
    d["algo"] = {k: v for k, v in d["algo"].items() if v is not None}
    d["algo"]["needs"] = dict(sorted((upstream or {}).items()))
    blob = json.dumps(d, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def compose(overrides: list[str]) -> Any:
    """conf/config.yaml composed with `overrides` (inside a running Hydra app or not)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from orchestrator.schema import register

    register()  # the schema the defaults list starts from
    if GlobalHydra.instance().is_initialized():
        return hydra_compose("config", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose("config", overrides=overrides)


def upstream_config(cfg: Config, spec: str, role: str) -> Config:
    """The config of the stage `spec` ("<algo> [key=value ...]") as `cfg` needs it in `role`; then
    `cfg.stage_overrides[<algo>]`, which apply to that method's stages anywhere above."""
    name, *overrides = spec.split()
    overrides += list(cfg.stage_overrides.get(name, []))
    bad = [o for o in overrides if "=" not in o or o.startswith(("+", "~"))]
    if bad:
        raise ConfigError(f"algo.needs.{role}: {bad[0]!r} is not a key=value override of the {name} stage")
    try:
        base = compose([f"algo={name}", f"scale={cfg.scale_name}"])
    except Exception as e:
        raise ConfigError(f"algo.needs.{role}: cannot compose stage {spec!r} ({e})") from None
    shared = {k: OmegaConf.structured(getattr(cfg, k)) if k in SECTIONS_SHARED else getattr(cfg, k) for k in SHARED}
    shared["stage_overrides"] = OmegaConf.create(cfg.stage_overrides)
    OmegaConf.set_struct(base, False)  # the shared stage_overrides and needs may add keys; validate checks them
    try:
        merged = OmegaConf.merge(base, shared, {"run_dir": cfg.run_dir}, OmegaConf.from_dotlist(overrides))
        return validate(merged)
    except Exception as e:
        raise ConfigError(f"algo.needs.{role} ({spec}): {_short(e)}") from None


@dataclass
class Upstream:
    """A finished stage that a run uses: where it is and how to read its outputs."""

    role: str
    name: str  # the stage's method (algo.name)
    run_id: str
    stage_hash: str
    uri: str
    cache: Path  # where its artifacts are downloaded
    reused: bool  # found finished in the store, not run for this one
    lineage: dict[str, str] = field(default_factory=dict)  # "demos.expert" -> run id, for every stage above

    def describe(self) -> str:
        return f"stage {self.role} ({self.name}, run {self.run_id})"

    def artifact(self, path: str) -> Path:
        """The artifact `path` of the stage's run, downloaded; a StageError naming both when it is not there."""
        from mlflow.tracking import MlflowClient

        local = self.cache / path
        if local.exists():
            return local
        self.cache.mkdir(parents=True, exist_ok=True)
        try:
            out = Path(MlflowClient(self.uri).download_artifacts(self.run_id, path, str(self.cache)))
        except Exception as e:
            hint = ""
            if "mlflow-artifacts" in str(e):
                hint = "; its artifacts are served by a tracking server: give that server as tracking.uri"
            raise StageError(
                f"{self.describe()}: artifact {path} is missing or unreadable ({_short(e)}){hint}"
            ) from None
        if not out.exists():
            raise StageError(f"{self.describe()}: artifact {path} is missing")
        return out

    def config(self) -> Config:
        path = self.artifact("config.json")
        try:
            return validate(json.loads(path.read_text()))
        except (json.JSONDecodeError, ConfigError) as e:
            raise StageError(f"{self.describe()}: artifact config.json is unreadable ({_short(e)})") from None

    def checkpoint(self) -> dict[str, Any]:
        """The stage's last checkpoint (state dicts, loaded with weights_only=True)."""
        from mlflow.tracking import MlflowClient

        try:
            names = [a.path for a in MlflowClient(self.uri).list_artifacts(self.run_id, "checkpoints")]
        except Exception as e:
            raise StageError(f"{self.describe()}: cannot list its checkpoints ({_short(e)})") from None
        names = sorted(n for n in names if re.search(r"ckpt-\d+\.pt$", n))
        if not names:
            raise StageError(f"{self.describe()}: artifact checkpoints/ckpt-*.pt is missing")
        path = self.artifact(names[-1])
        try:
            return checkpoint.load(path)
        except checkpoint.CheckpointError as e:  # truncated, not a weights file, not a dict of states
            raise StageError(f"{self.describe()}: artifact {names[-1]} ({path}): {e.message}") from None

    def metrics(self) -> dict[str, float]:
        from mlflow.tracking import MlflowClient

        return dict(MlflowClient(self.uri).get_run(self.run_id).data.metrics)


def _short(e: BaseException) -> str:
    return str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__


def find_finished(client: MlflowClient, stage_hash: str) -> str | None:
    """The newest FINISHED run with this stage hash, in any experiment of the store."""
    experiments = [e.experiment_id for e in client.search_experiments()]
    if not experiments:
        return None
    runs = client.search_runs(
        experiments,
        filter_string=f"tags.stage_hash = '{stage_hash}' and attributes.status = 'FINISHED'",
        order_by=["attributes.start_time DESC"],
        max_results=1,
    )
    return runs[0].info.run_id if runs else None


def resolve(cfg: Config, uri: str, workdir: Path, experiment: str, log=print) -> dict[str, Upstream]:
    """Every need of `cfg`, reused from the store or run now (upstream first); role → Upstream."""
    return {role: ensure(role, spec, cfg, uri, workdir, experiment, log) for role, spec in cfg.algo.needs.items()}


def ensure(role: str, spec: str, cfg: Config, uri: str, workdir: Path, experiment: str, log=print) -> Upstream:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    cache = workdir / "upstream" / role
    run_id = RUN_ID.fullmatch(spec.strip())
    if run_id:
        return _existing(client, role, run_id.group(1), uri, cache)
    up = upstream_config(cfg, spec, role)
    above = resolve(up, uri, workdir, experiment, log)
    h = config_hash(up, {r: u.stage_hash for r, u in above.items()})
    lineage = {r: u.run_id for r, u in above.items()}
    for r, u in above.items():
        lineage.update({f"{r}.{k}": v for k, v in u.lineage.items()})
    found = find_finished(client, h)
    if found:
        log(f"stage {role}: reusing {up.algo.name} run {found} (hash {h})")
        return Upstream(role, up.algo.name, found, h, uri, cache, True, lineage)
    from orchestrator.build import RUN_FILE, run

    up.run_dir = str(workdir / "stages" / f"{up.algo.name}-{h[:8]}")
    # A stage cut short here before (its run FAILED or never ended) continues from its last checkpoint.
    up.resume = checkpoint.latest(Path(up.run_dir) / "checkpoints") is not None
    up.tracking.uri = uri
    up.tracking.experiment = experiment
    up.tracking.run_name = f"{up.algo.name} stage {h[:8]}"
    how = "resuming it from its last checkpoint" if up.resume else "training it"
    log(f"stage {role}: no finished {up.algo.name} run with hash {h} in {uri}; {how} in {up.run_dir}")
    run(up, upstream=above, stage_hash=h)
    new_id = json.loads((Path(up.run_dir) / RUN_FILE).read_text())["run_id"]
    return Upstream(role, up.algo.name, new_id, h, uri, cache, False, lineage)


def _existing(client: MlflowClient, role: str, run_id: str, uri: str, cache: Path) -> Upstream:
    try:
        r = client.get_run(run_id)
    except Exception as e:
        raise StageError(f"stage {role}: run {run_id} is not in {uri} ({_short(e)})") from None
    if r.info.status != "FINISHED":
        raise StageError(f"stage {role}: run {run_id} is {r.info.status}, not FINISHED")
    tags = r.data.tags
    lineage = {
        k.removeprefix("upstream."): v
        for k, v in tags.items()
        if k.startswith("upstream.") and not k.endswith(".reused")
    }
    name = tags.get("algo", "?")
    return Upstream(role, name, run_id, tags.get("stage_hash", run_id), uri, cache, True, lineage)


def lineage_tags(upstream: dict[str, Upstream]) -> dict[str, str]:
    """Tags that say which stages a run used: upstream.<role>[.<role>...] = run id, and expert_run_id."""
    tags: dict[str, str] = {}
    for role, u in upstream.items():
        tags[f"upstream.{role}"] = u.run_id
        tags[f"upstream.{role}.reused"] = str(u.reused).lower()
        tags.update({f"upstream.{role}.{k}": v for k, v in u.lineage.items()})
    for key, value in list(tags.items()):
        if key == "upstream.expert" or key.endswith(".expert"):
            tags["expert_run_id"] = value
    return tags
