"""Build the experiment from a validated config and run it: tracker, runtime, trainer."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from orchestrator import checkpoint, stages
from orchestrator.components import load_world
from orchestrator.loop import Trainer
from orchestrator.runtime.base import Runtime
from orchestrator.schema import Config
from orchestrator.stages import StageError, Upstream
from orchestrator.summary import closing, where_to_watch
from orchestrator.tracking.base import NoOpTracker, Tracker, flatten

RUN_FILE = "run.json"


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def build_tracker(
    cfg: Config, run_id: str | None, parent_run_id: str | None = None, extra_tags: dict[str, str] | None = None
) -> Tracker:
    if not cfg.tracking.enabled:
        return NoOpTracker()
    from orchestrator.tracking.mlflow import MlflowTracker

    tags = {"git_commit": git_commit(), "stage": cfg.algo.name, "algo": cfg.algo.name, "preset": cfg.preset}
    tags["host"] = socket.gethostname()
    tags.update(extra_tags or {})
    return MlflowTracker(
        uri=cfg.tracking.uri,
        experiment=cfg.tracking.experiment or cfg.preset,
        run_name=cfg.tracking.run_name,
        run_id=run_id,
        parent_run_id=parent_run_id,
        tags=tags,
        run_dir=Path(cfg.run_dir),
    )


def build_runtime(cfg: Config) -> Runtime:
    """The backend named by runtime._target_, given the runtime group's fields."""
    return instantiate(OmegaConf.structured(cfg.runtime), _convert_="all")


def hydra_record() -> list[Path]:
    """Hydra's own record of a command-line run: the composed config, the overrides as typed and Hydra's
    settings (`<hydra output dir>/.hydra/*.yaml`); none outside a Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    try:
        hc = HydraConfig.get()
    except ValueError:
        return []
    if not hc.output_subdir:
        return []
    where = Path(hc.runtime.output_dir) / hc.output_subdir
    return [where / name for name in ("config.yaml", "overrides.yaml", "hydra.yaml") if (where / name).exists()]


def store_of(cfg: Config) -> str:
    """The tracking store this run writes to (where its upstream stages are looked for and kept)."""
    from orchestrator.tracking.mlflow import embedded_uri

    return cfg.tracking.uri or embedded_uri(cfg.run_dir)


def run(
    cfg: Config,
    parent_run_id: str | None = None,
    upstream: dict[str, Upstream] | None = None,
    stage_hash: str | None = None,
) -> dict[str, float]:
    """Train `cfg`'s method; its upstream stages (`algo.needs`) are reused from the store or run first."""
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    character, _ = load_world(cfg)  # a clip that does not load fails here, before any process starts
    if upstream is None and cfg.algo.needs:
        if not cfg.tracking.enabled:
            raise StageError(f"the {cfg.algo.name} method reads upstream stages from MLflow: tracking.enabled=false")
        experiment = cfg.tracking.experiment or cfg.preset
        upstream = stages.resolve(cfg, store_of(cfg), run_dir, experiment, log=_log)
    upstream = upstream or {}
    if stage_hash is None:
        stage_hash = stages.config_hash(cfg, {r: u.stage_hash for r, u in upstream.items()})
    run_file = run_dir / RUN_FILE
    resume_from = checkpoint.latest(run_dir / "checkpoints") if cfg.resume else None
    run_id = json.loads(run_file.read_text())["run_id"] if cfg.resume and run_file.exists() else None
    if resume_from is not None:  # a checkpoint that does not fit is refused before the run is reopened
        from orchestrator import preflight

        preflight.resume_checkpoint(cfg, character)
    if cfg.resume and resume_from is None:
        print(f"resume: no checkpoint in {run_dir / 'checkpoints'}; starting from scratch", file=sys.stderr)
    tags = {"stage_hash": stage_hash, **stages.lineage_tags(upstream)}
    tracker = build_tracker(cfg, run_id, parent_run_id, tags)
    if run_id is None:
        resolved: dict[str, Any] = asdict(cfg)
        tracker.log_params(flatten(resolved))
        tracker.log_dict(resolved, "config.json")
        for path in hydra_record():
            tracker.log_artifact(str(path), "hydra")
    run_file.write_text(json.dumps({"run_id": tracker.run_id}))
    runtime = build_runtime(cfg)
    status = "FAILED"
    try:
        trainer = Trainer(cfg, runtime, tracker, character, upstream)
        _log(where_to_watch(cfg, tracker, runtime))
        if resume_from is not None:
            trainer.restore(resume_from)
            print(f"resumed from {resume_from} at iteration {trainer.state.iteration}", file=sys.stderr)
        summary = trainer.run()
        status = "FINISHED"
        print(closing(cfg, tracker, trainer.state.baseline, summary, trainer.model_uri), flush=True)
        return summary
    finally:
        tracker.close(status)
        # A run created late (the server was down at the start) has its id only now.
        run_file.write_text(json.dumps({"run_id": tracker.run_id}))
        runtime.shutdown()
