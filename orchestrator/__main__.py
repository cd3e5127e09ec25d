"""`python -m orchestrator [+experiment=NAME] [key=value ...] [-m]`: compose, validate, build, run."""

from __future__ import annotations

import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from orchestrator.schema import ConfigError, register, validate

register()


def _run_name(cfg) -> str:
    """What the run is: its method and seed, then the overrides it was given (a sweep point's include what
    varies), e.g. `controlvae seed=0` or `physicsvae seed=1 algo.vae.alpha=0.01`."""
    try:
        overrides = HydraConfig.get().overrides.task
    except ValueError:
        overrides = []
    hidden = ("+experiment", "hydra.", "run_dir", "progress", "seed=", "algo=")
    return " ".join([cfg.algo.name, f"seed={cfg.seed}", *(o for o in overrides if not o.startswith(hidden))])


def _is_multirun() -> bool:
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(dcfg: DictConfig) -> float | None:
    try:
        cfg = validate(dcfg)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        sys.exit(2)
    if cfg.tracking.run_name is None:
        cfg.tracking.run_name = _run_name(cfg)
    from orchestrator.build import run
    from orchestrator.sweep import parent_of

    parent = parent_of(HydraConfig.get().sweep.dir) if _is_multirun() else None
    if parent is not None:
        # A point of a sweep: a child of the sweep's parent run, in the sweep's store.
        cfg.tracking.uri = cfg.tracking.uri or parent["uri"]
        cfg.tracking.experiment = parent["experiment"]
    from orchestrator.stages import StageError

    try:
        summary = run(cfg, parent_run_id=parent["parent_run_id"] if parent else None)
    except (StageError, ConfigError) as e:
        print(f"stage error: {e}" if isinstance(e, StageError) else f"config error: {e}", file=sys.stderr)
        sys.exit(2)
    return summary.get("eval/time_until_fall_mean")


if __name__ == "__main__":
    main()
