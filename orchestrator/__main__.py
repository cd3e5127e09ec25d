"""`python -m orchestrator [+experiment=NAME] [key=value ...] [-m]`: compose, validate, check, build, run.

Bad input ends the run with exit status 2 and one line on stderr naming the key, file or address:
`config error: ...` for a config value (at composition), `error: ...` for input that the config names
but that cannot be used (a malformed clip or character file, a checkpoint that does not fit, a Ray
address where nothing answers: `orchestrator.preflight`), `stage error: ...` for an upstream stage.
"""

from __future__ import annotations

import sys
from typing import NoReturn

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from orchestrator.compose import register, validate
from orchestrator.schema import ConfigError

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
    from orchestrator.sweep.callback import parent_of

    parent = parent_of(HydraConfig.get().sweep.dir) if _is_multirun() else None
    try:
        cfg = validate(dcfg)
    except ConfigError as e:
        _fail(f"config error: {e}", parent)
    if cfg.tracking.run_name is None:
        cfg.tracking.run_name = _run_name(cfg)
    from orchestrator.build import run

    if parent is not None:
        # A point of a sweep: a child of the sweep's parent run, in the sweep's store.
        cfg.tracking.uri = cfg.tracking.uri or parent["uri"]
        cfg.tracking.experiment = parent["experiment"]
    from orchestrator.checkpoint import CheckpointError
    from orchestrator.preflight import InputError, check
    from orchestrator.upstream import StageError
    from workers.body.character import CharacterError
    from workers.motion.errors import ClipError

    # The line's prefix per kind of bad input; clips, characters and checkpoints that an upstream stage
    # run here reads are ones `check` did not see.
    prefixes = {
        StageError: "stage error: ",
        ConfigError: "config error: ",
        InputError: "error: ",
        ClipError: "error: clip ",
        CharacterError: "error: character ",
        CheckpointError: "error: checkpoint ",
    }
    try:
        check(cfg)  # before anything is started or written
        summary = run(cfg, parent_run_id=parent["parent_run_id"] if parent else None)
    except tuple(prefixes) as e:
        prefix = next(p for kind, p in prefixes.items() if isinstance(e, kind))
        _fail(f"{prefix}{e}", parent)
    return summary.get("eval/time_until_fall_mean")


def _fail(line: str, parent: dict | None = None) -> NoReturn:
    """One line and exit status 2; a sweep point also marks the sweep's parent run FAILED (the multirun
    ends here, so the sweep's own end, which would close it, never comes)."""
    print(line, file=sys.stderr)
    if parent is not None:
        try:
            from orchestrator.tracking.query import set_terminated

            set_terminated(parent["uri"], parent["parent_run_id"], "FAILED")
        except Exception:  # noqa: BLE001 - the store is away: the parent stays RUNNING, the line above says why
            pass
    sys.exit(2)


if __name__ == "__main__":
    main()
