"""Build the experiment from a validated config and run it: its upstream stages, run logger, runtime and trainer.

`run(cfg)` trains `cfg`'s method into one MLflow run (reopened on resume), after resolving the
stages it needs (`orchestrator.stages`, which trains a missing one through `train_stage`);
`untracked_trainer` wires the same trainer without tracking, for the benchmarks.
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import sys
import threading
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from orchestrator import checkpoint, preflight, stages
from orchestrator.console import closing, where_to_watch
from orchestrator.provenance import git_commit
from orchestrator.runtime.base import Runtime
from orchestrator.schema import Config
from orchestrator.tracking.base import NoOpLogger, RunLogger, flatten
from orchestrator.tracking.uri import scrub, scrub_file, scrub_tree, store_uri
from orchestrator.trainer import Trainer
from orchestrator.upstream import StageError, Upstream
from orchestrator.world import load_character, load_character_and_library


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def build_logger(
    cfg: Config, run_id: str | None, parent_run_id: str | None = None, extra_tags: dict[str, str] | None = None
) -> RunLogger:
    if not cfg.tracking.enabled:
        return NoOpLogger()
    from orchestrator.tracking.mlflow import MlflowLogger  # loads mlflow: only when tracking

    tags = {"git_commit": git_commit(), "stage": cfg.algo.name, "algo": cfg.algo.name, "preset": cfg.preset}
    tags["host"] = socket.gethostname()
    tags.update(extra_tags or {})
    return MlflowLogger(
        uri=cfg.tracking.uri,
        experiment=cfg.tracking.experiment or cfg.preset,
        run_name=cfg.tracking.run_name,
        run_id=run_id,
        parent_run_id=parent_run_id,
        tags=tags,
        run_dir=Path(cfg.run_dir),
        artifact_timeout_s=cfg.tracking.artifact_timeout_s,
        artifact_tries=cfg.tracking.artifact_tries,
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
    output_dir = OmegaConf.select(hc, "runtime.output_dir", default=None, throw_on_missing=False)
    if not hc.output_subdir or not output_dir:  # composed by hydra.compose, not run by Hydra: no record
        return []
    where = Path(output_dir) / hc.output_subdir
    return [where / name for name in ("config.yaml", "overrides.yaml", "hydra.yaml") if (where / name).exists()]


def scrub_hydra_record() -> None:
    """Hydra's record on disk with the passwords of the URIs in it masked (the overrides as typed may hold
    `tracking.uri=postgresql://user:pw@...`): the password stays only where the user keeps it."""
    for path in hydra_record():
        scrub_file(path)


def train_stage(cfg: Config, upstream: dict[str, Upstream], stage_hash: str) -> str:
    """Train an upstream stage that the store does not hold (`stages.resolve` asks); its MLflow run's id."""
    run(cfg, upstream=upstream, stage_hash=stage_hash)
    return json.loads((Path(cfg.run_dir) / checkpoint.RUN_FILE).read_text())["run_id"]


def untracked_trainer(cfg: Config) -> tuple[Runtime, Trainer]:
    """The runtime and the trainer of `cfg` (a method without upstream stages), logging nowhere: the benchmarks'
    wiring. The caller shuts the runtime down."""
    runtime = build_runtime(cfg)
    try:
        return runtime, Trainer(cfg, runtime, NoOpLogger(), load_character(cfg))
    except BaseException:
        runtime.shutdown()
        raise


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) stopped a run: the checkpoint being written was finished or deleted, and the MLflow
    run is marked KILLED. `iteration`: the iterations that run had done; `run_dir`: its run directory (an
    upstream stage's, when one was being trained)."""

    def __init__(self, iteration: int, run_dir: Path):
        super().__init__(iteration, run_dir)
        self.iteration = iteration
        self.run_dir = run_dir


def run(
    cfg: Config,
    parent_run_id: str | None = None,
    upstream: dict[str, Upstream] | None = None,
    stage_hash: str | None = None,
) -> dict[str, float]:
    """Train `cfg`'s method; its upstream stages (`algo.needs`) are reused from the store or run first.

    The run directory is locked for the run (`checkpoint.lock_run_dir`): a second command given the same
    one stops with `checkpoint.RunDirBusy` before anything is written. Interrupted, it raises `Interrupted`."""
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    with checkpoint.lock_run_dir(run_dir):
        return _run(cfg, parent_run_id, upstream, stage_hash)


def _run(
    cfg: Config, parent_run_id: str | None, upstream: dict[str, Upstream] | None, stage_hash: str | None
) -> dict[str, float]:
    run_dir = Path(cfg.run_dir)
    torch.manual_seed(cfg.seed)
    character, _ = load_character_and_library(cfg)  # a clip that does not load fails here, before any process starts
    if upstream is None and cfg.algo.needs:
        if not cfg.tracking.enabled:
            raise StageError(f"the {cfg.algo.name} method reads upstream stages from MLflow: tracking.enabled=false")
        experiment = cfg.tracking.experiment or cfg.preset
        upstream = stages.resolve(cfg, store_uri(cfg.tracking.uri, run_dir), run_dir, experiment, train_stage, log=_log)
    upstream = upstream or {}
    if stage_hash is None:
        stage_hash = stages.config_hash(cfg, {r: u.stage_hash for r, u in upstream.items()})
    run_file = run_dir / checkpoint.RUN_FILE
    run_id = json.loads(run_file.read_text())["run_id"] if cfg.resume and run_file.exists() else None
    if run_id and cfg.tracking.enabled and preflight.missing_run(cfg, run_id):
        # A stage cut short whose run the store lost (a command's own run is refused by `preflight.check`):
        # made again whole, params and config, and continued from its checkpoint.
        _log(f"resume: run {run_id} is not in the store; a new run continues it from its last checkpoint")
        run_id = None
    # The newest checkpoint that fits, each newer one that does not named; none fits: refused before the run
    # is reopened. A crash's leftovers (a `.tmp`, checkpoints beyond algo.loop.checkpoint_keep) go at the
    # first save.
    resume_from = preflight.resume_checkpoint(cfg, character, log=_log) if cfg.resume else None
    if cfg.resume and resume_from is None:
        print(f"resume: no checkpoint in {run_dir / 'checkpoints'}; starting from scratch", file=sys.stderr)
    tags = {"stage_hash": stage_hash, **stages.lineage_tags(upstream)}
    logger = build_logger(cfg, run_id, parent_run_id, tags)
    status, runtime, trainer = "FAILED", None, None
    try:
        if run_id is None:
            resolved: dict[str, Any] = scrub_tree(asdict(cfg))  # tracking.uri's password masked
            logger.log_params(flatten(resolved))
            logger.log_dict(resolved, "config.json")
            for path in hydra_record():  # as typed, the overrides may hold the password: a scrubbed copy
                logger.log_text(scrub(path.read_text()), f"hydra/{path.name}")
        scrub_hydra_record()
        run_file.write_text(json.dumps({"run_id": logger.run_id}))
        runtime = build_runtime(cfg)
        sigterm = signal.getsignal(signal.SIGTERM)
        trainer = Trainer(cfg, runtime, logger, character, upstream)
        if threading.current_thread() is threading.main_thread():  # ray.init sets its own: exit at once, FAILED
            signal.signal(signal.SIGTERM, sigterm)
        _log(where_to_watch(cfg, logger, runtime))
        if resume_from is not None:
            resume_from = _restore(trainer, resume_from)
            print(f"resumed from {resume_from} at iteration {trainer.state.iteration}", file=sys.stderr)
        summary = trainer.run()
        status = "FINISHED"
        print(closing(cfg, logger, trainer.state.baseline, summary, trainer.model_uri), flush=True)
        return summary
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (orchestrator.__main__); a stage's own is passed on
        status = "KILLED"
        if isinstance(e, Interrupted):
            raise
        raise Interrupted(trainer.state.iteration if trainer is not None else 0, run_dir) from None
    except OSError as e:
        if e.errno not in checkpoint.DISK_ERRORS:
            raise
        raise _disk_error(e, run_dir, logger) from None
    finally:
        with _shielded(status == "KILLED"):
            with _kept_going(status == "FAILED"):
                logger.close(status)
                # A run created late (the server was down at the start) has its id only now.
                run_file.write_text(json.dumps({"run_id": logger.run_id}))
            if runtime is not None:
                runtime.shutdown()


def _disk_error(e: OSError, run_dir: Path, logger: RunLogger) -> checkpoint.DiskError:
    """A disk that filled up or turned read-only under the run: the reason tagged on its run (`last_failure`, when the
    store can still take it), and one line saying which file, what stays and how to go on."""
    reason = f"{e.filename or run_dir}: {e.strerror}"
    with contextlib.suppress(Exception):  # a store on the same full disk: the line below says it all
        logger.set_tags({"last_failure": reason})
    last = checkpoint.latest(run_dir / "checkpoints")
    kept = f"{last.name} stays, the last complete checkpoint" if last else "no checkpoint was complete yet"
    return checkpoint.DiskError(
        f"{reason} (the file being written was discarded; {kept}); the run is FAILED: free space, then resume with "
        f"run_dir={run_dir} resume=true"
    )


@contextlib.contextmanager
def _kept_going(on: bool) -> Iterator[None]:
    """The close of a run that failed on a full disk, whose own writes (its store, its run file) may fail too:
    what does not go is warned about, so that the reason above stays the command's last word."""
    if not on:
        yield
        return
    try:
        yield
    except OSError as e:
        print(f"warning: closing the run: {e}", file=sys.stderr)


@contextlib.contextmanager
def _shielded(on: bool) -> Iterator[None]:
    """Ctrl-C and SIGTERM ignored while a run that was interrupted closes (a second Ctrl-C, pressed while it
    does, would leave its MLflow run RUNNING); only in the main thread, where signals are handled."""
    if not on or threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def _restore(trainer: Trainer, first: Path) -> Path:
    """Restore `trainer` from `first` or, if that does not fit (checked only now for a method with upstream
    stages), from the newest older checkpoint that does; the one used. CheckpointError if none fits."""
    older = [p for p in checkpoint.newest_first(first.parent) if p <= first]
    for path in older:
        try:
            trainer.restore(path)
            return path
        except checkpoint.CheckpointError as e:
            if path == older[-1]:
                raise
            _log(f"resume: skipping checkpoint {e}")
    raise checkpoint.CheckpointError(first, "no such file")
