"""`python -m orchestrator [+experiment=NAME] [key=value ...] [-m]`: compose, validate, check, build, run.

Bad input ends the run with exit status 2 and one line on stderr naming the key, file or address:
`config error: ...` for a config value (at composition), `error: ...` for input that the config names
but that cannot be used (a malformed clip or character file, a checkpoint that does not fit, a Ray
address where nothing answers: `orchestrator.preflight`; a run directory another command is running in),
`stage error: ...` for an upstream stage. Ctrl-C (or SIGTERM) ends a run with exit status 130, its MLflow
run KILLED, and one line: where it stopped and the command that resumes it. Any other exception is Hydra's
to report (exit status 1; a parallel sweep's other points finish first). No password of a URI in the
overrides (`tracking.uri`, `runtime.address`) reaches any of these, the log, what Hydra writes to stderr or
Hydra's record of the run (`.hydra/*.yaml`, scrubbed first thing): it is masked (`user:***@`), and a resume
line asks for it through MLflow's environment variable.
"""

from __future__ import annotations

import shlex
import shutil
import signal
import sys
from pathlib import Path
from typing import NoReturn

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from orchestrator.compose import register, validate
from orchestrator.schema import ConfigError
from orchestrator.tracking.uri import ScrubbedStream, hide, scrub

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
    from orchestrator.build import scrub_hydra_record

    uris = [OmegaConf.select(dcfg, key, default=None) for key in ("tracking.uri", "runtime.address")]
    for uri in uris:  # masked in every log record from now on
        hide(uri)
    if any(uri and scrub(uri) != uri for uri in uris) and not isinstance(sys.stderr, ScrubbedStream):
        sys.stderr = ScrubbedStream(sys.stderr)  # and in what Hydra writes there itself when a job fails
    scrub_hydra_record()  # written by Hydra before this call; kept as is were the run refused below
    return _main(dcfg)


def _main(dcfg: DictConfig) -> float | None:
    from orchestrator.sweep.callback import parent_of

    parent = parent_of(HydraConfig.get().sweep.dir) if _is_multirun() else None
    record = None if parent is not None else _own_record(dcfg)
    try:
        cfg = validate(dcfg)
    except ConfigError as e:
        _fail(f"config error: {e}", parent, record=record)
    if cfg.tracking.run_name is None:
        cfg.tracking.run_name = _run_name(cfg)
    from orchestrator.build import run

    if parent is not None:
        # A point of a sweep: a child of the sweep's parent run, in the sweep's store.
        cfg.tracking.uri = cfg.tracking.uri or parent["uri"]
        cfg.tracking.experiment = parent["experiment"]
    from orchestrator.checkpoint import CheckpointError, DiskError, RunDirBusy
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
        RunDirBusy: "error: ",
        DiskError: "error: ",
    }
    signal.signal(signal.SIGTERM, _interrupt)  # `kill`, a scheduler's stop: as Ctrl-C
    try:
        check(cfg)  # before anything is started or written
        summary = run(cfg, parent_run_id=parent["parent_run_id"] if parent else None)
    except tuple(prefixes) as e:
        prefix = next(p for kind, p in prefixes.items() if isinstance(e, kind))
        _fail(f"{prefix}{e}", parent, record=record)
    except KeyboardInterrupt as e:  # orchestrator.build.Interrupted once training has started
        _fail(_interrupted_line(cfg, e), parent, status="KILLED", code=130)
    return summary.get("eval/time_until_fall_mean")


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _interrupted_line(cfg, e: KeyboardInterrupt) -> str:
    """`interrupted at iteration N (a resume starts from ckpt-M.pt); resume with: python -m orchestrator
    <the same overrides> run_dir=<dir> resume=true`; for an upstream stage cut short, its checkpoint's path."""
    from orchestrator.checkpoint import latest

    try:
        overrides = list(HydraConfig.get().overrides.task)
    except ValueError:
        overrides = []
    kept = [o for o in overrides if not o.lstrip("+~").startswith(("run_dir=", "resume="))]
    command = shlex.join(["python", "-m", "orchestrator", *kept, f"run_dir={cfg.run_dir}", "resume=true"])
    if scrub(command) != command:  # a password in an override: masked, so the command asks for it
        command = f"MLFLOW_TRACKING_PASSWORD=... {scrub(command)}"
    run_dir = Path(getattr(e, "run_dir", cfg.run_dir))
    last = latest(run_dir / "checkpoints")
    saved = "from scratch: no checkpoint yet" if last is None else f"from {last.name}"
    if last is not None and run_dir != Path(cfg.run_dir):
        saved = f"the stage in {run_dir} from {last.name}"
    where = f"at iteration {e.iteration}" if hasattr(e, "iteration") else "before training started"
    return f"interrupted {where} (a resume starts {saved}); resume with: {command}"


def _own_record(dcfg: DictConfig) -> Path | None:
    """Hydra's output folder when it is the run directory (`run_dir=` given, or neither given) and holds nothing but
    Hydra's record of this command (a new run directory): what a refused command removes, leaving no trace."""
    try:
        out = Path(HydraConfig.get().runtime.output_dir).resolve()
        run_dir = Path(str(OmegaConf.select(dcfg, "run_dir"))).resolve()
    except Exception:  # noqa: BLE001 - outside a Hydra run (tests call main's body): nothing of Hydra's to remove
        return None
    ours = {".hydra", f"{HydraConfig.get().job.name}.log"}
    return out if out == run_dir and out.is_dir() and {p.name for p in out.iterdir()} <= ours else None


def _fail(
    line: str, parent: dict | None = None, status: str = "FAILED", code: int = 2, record: Path | None = None
) -> NoReturn:
    """One line and exit status `code`; a sweep point also marks the sweep's parent run `status` (the
    multirun ends here, so the sweep's own end, which would close it, never comes). `record`: the new run
    directory Hydra made for a command refused before it started (`_own_record`), removed."""
    print(scrub(line), file=sys.stderr)
    if record is not None and {p.name for p in record.iterdir()} <= {".hydra", f"{HydraConfig.get().job.name}.log"}:
        shutil.rmtree(record, ignore_errors=True)
        for folder in record.parents:  # outputs/<preset>/ made for it, when empty now
            if folder == Path.cwd().resolve() or not folder.is_relative_to(Path.cwd().resolve()):
                break
            try:
                folder.rmdir()
            except OSError:
                break
    if parent is not None:
        try:
            from orchestrator.tracking.query import set_terminated

            set_terminated(parent["uri"], parent["parent_run_id"], status)
        except Exception:  # noqa: BLE001 - the store is away: the parent stays RUNNING, the line above says why
            pass
    sys.exit(code)


def _check_output_dir(argv: list[str]) -> None:
    """One line and exit 2 when the folder Hydra is about to write its record into (`hydra.run.dir=`, else
    `run_dir=`, else outputs/ here) cannot be written to (a read-only mount, no permission), before Hydra tries and
    fails with a traceback; not for a multirun, whose folders are its own."""
    from orchestrator.checkpoint import unwritable

    if any(a in ("-m", "--multirun") for a in argv):
        return
    given = dict(a.split("=", 1) for a in argv if a.startswith(("hydra.run.dir=", "run_dir=")))
    key = "hydra.run.dir" if "hydra.run.dir" in given else "run_dir" if "run_dir" in given else None
    where = given[key] if key else "outputs"
    problem = unwritable(where)
    if problem:
        what = f"{key}={where}" if key else f"{Path.cwd()}: Hydra's outputs/ folder, where run_dir goes by default,"
        print(f"error: {what}: cannot write there ({problem}); give a run_dir= you can write to", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    _check_output_dir(sys.argv[1:])
    main()
