"""What a run reads, checked before anything starts: bad input is one line naming its file, key or address.

`check(cfg)` runs after the config is validated and before `orchestrator.build.run`, that is before
the tracker creates (or, to resume, reopens) an MLflow run, before Ray is started or joined, and before
anything is written to the run directory, so that bad input leaves everything already saved as it was:

- the character file is our humanoid's skeleton (`workers.body.character`) and every clip loads and is
  plausible (`workers.motion.clip.check_plausible`): the same checks as `python -m orchestrator.clips check`;
- `tracking.uri` has a scheme MLflow knows (checked at composition too; a sweep point takes its parent's);
- `runtime.address` answers within `runtime.connect_timeout_s` (runtime=ray);
- a GPU asked for (`runtime.learner_device=cuda`, `runtime.learner_gpus`) is one this machine has (the
  local runtime, or a Ray started for the run; a cluster's GPUs are counted when Ray reserves them);
- with `resume=true`, a checkpoint in the run directory is complete, a weights file, written by this
  method, and fits this config's networks: its states are loaded into the method's components built here
  (for methods without upstream stages; those that have them are checked when the trainer restores). The
  newest that does is the one a resume starts from; an error only when none does.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import torch

from orchestrator import checkpoint
from orchestrator.algos.base import method_class
from orchestrator.runtime.base import uses_ray
from orchestrator.schema import Config, ConfigError
from orchestrator.tracking.uri import tracking_uri_error
from orchestrator.trainer import LoopState
from orchestrator.world import load_character_and_library
from workers.body.character import Character, CharacterError
from workers.motion.errors import ClipError


class InputError(RuntimeError):
    """Input a run cannot use; the message is one line naming the file, key or address."""


def check(cfg: Config) -> None:
    """InputError (ConfigError for a config value) for the first input of `cfg` that a run cannot use."""
    if cfg.tracking.enabled and cfg.tracking.uri:
        problem = tracking_uri_error(cfg.tracking.uri)
        if problem:
            raise ConfigError(f"tracking.uri: {problem}")
    learner_devices(cfg)
    character = character_and_clips(cfg)
    if cfg.runtime.address and cfg.runtime._target_.endswith("RayRuntime"):
        from orchestrator.runtime.ray import AddressError, check_address

        try:
            check_address(cfg.runtime.address, cfg.runtime.connect_timeout_s)
        except AddressError as e:
            raise InputError(str(e)) from None
    if cfg.resume:
        resume_run(cfg)
        resume_checkpoint(cfg, character)


def learner_devices(cfg: Config) -> None:
    """ConfigError naming the key when the learners are to compute on a GPU that is not there."""
    r = cfg.runtime
    here = not uses_ray(r) or not r.address  # the learners run on this machine
    gpus = torch.cuda.device_count() if here else None
    seen = f"torch {torch.__version__} sees {gpus} GPU(s), CUDA available: {torch.cuda.is_available()}"
    if here and r.learner_device == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"runtime.learner_device=cuda: no GPU on this machine ({seen})")
    if here and uses_ray(r) and r.learner_gpus > 0 and not gpus:
        raise ConfigError(f"runtime.learner_gpus={r.learner_gpus:g}: no GPU on this machine ({seen})")
    if not here and r.learner_device == "cuda" and r.learner_gpus <= 0:
        raise ConfigError(
            "runtime.learner_device=cuda: a learner actor on the cluster at runtime.address sees only the GPUs Ray "
            "assigns it; set runtime.learner_gpus (e.g. 1)"
        )


def character_and_clips(cfg: Config) -> Character:
    """The character and the motion library load (the library is built, and its clips cached, here)."""
    try:
        character, _ = load_character_and_library(cfg)
    except CharacterError as e:
        raise InputError(f"character.xml={cfg.character.xml}: {e.message}") from None
    except ClipError as e:
        raise InputError(f"clip {e}") from None
    return character


def resume_run(cfg: Config) -> str | None:
    """The MLflow run a resume continues (run_dir/run.json), or None; InputError if the file is unreadable."""
    path = Path(cfg.run_dir) / checkpoint.RUN_FILE
    if not path.exists():
        return None
    try:
        run_id = json.loads(path.read_text())["run_id"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, TypeError, KeyError):
        run_id = False
    if not (run_id is None or isinstance(run_id, str)):  # None: the run was not tracked
        raise InputError(f'{path}: not a run file ({{"run_id": "<MLflow run id>"}}); resume=true reads it')
    return run_id


def resume_checkpoint(cfg: Config, character: Character, log: Callable[[str], None] | None = None) -> Path | None:
    """The checkpoint a resume starts from: the newest in run_dir/checkpoints that loads into this config's
    components, each newer one that does not said in one line to `log`. InputError naming the file and what
    is wrong (for a size mismatch, the tensor and both shapes) when none does. The files are only read."""
    paths = checkpoint.newest_first(Path(cfg.run_dir) / "checkpoints")
    if not paths:
        return None
    method = method_class(cfg.algo._target_)(cfg, character, None)
    components = [] if method.needs else method.components()  # with upstream stages: built later, from them
    targets = None
    errors: list[checkpoint.CheckpointError] = []
    for path in paths:
        try:
            state = checkpoint.load(path)
            checkpoint.check_layout(path, state, [c.key for c in components])
            if method.needs:  # its components fit or not once the trainer restores them
                return path
            try:
                LoopState(**state["loop"])
            except TypeError as e:
                raise checkpoint.CheckpointError(path, f"loop: {e}") from None
            if targets is None:  # built as the trainer builds them, without touching torch's threads or RNG
                threads = torch.get_num_threads()
                with torch.random.fork_rng(devices=[]):
                    targets = {c.key: c.cls(*c.args, **c.kwargs) for c in components}
                torch.set_num_threads(threads)
            checkpoint.check_restore(path, state, {"method": method, **targets})
            return path
        except checkpoint.CheckpointError as e:
            errors.append(e)
            if log is not None:
                log(f"resume: skipping checkpoint {e}")
    if len(paths) == 1:
        raise InputError(f"checkpoint {errors[0]} (resume=true; the file is left as it is)")
    raise InputError(
        f"checkpoint {errors[0]} (and the {len(paths) - 1} before it do not load either; resume=true; "
        "the files are left as they are)"
    )
