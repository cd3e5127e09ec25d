"""What a run reads, checked before anything starts: bad input is one line naming its file, key or address.

`check(cfg)` runs after the config is validated and before `orchestrator.build.run`, that is before
the tracker creates (or, to resume, reopens) an MLflow run, before Ray is started or joined, and before
anything is written to the run directory, so that bad input leaves everything already saved as it was:

- the character file is our humanoid's skeleton (`workers.body.character`) and every clip loads and is
  plausible (`workers.motion.clip.check_plausible`): the same checks as `python -m orchestrator.clips check`;
- `tracking.uri` has a scheme MLflow knows (checked at composition too; a sweep point takes its parent's),
  and an MLflow server there that asks for a user accepts this process's (MLFLOW_TRACKING_USERNAME/PASSWORD)
  and lets it create runs in the run's experiment (`tracking.experiment`, else the preset's name);
- `runtime.address` answers within `runtime.connect_timeout_s` (runtime=ray);
- a GPU asked for (`runtime.learner_device=cuda`, `runtime.learner_gpus`) is one this machine has (the
  local runtime, or a Ray started for the run) or, at a cluster's `runtime.address`, one the cluster has;
  so is the warp simulator's (`sim.device`);
- the method's replay buffers (`algo.loop.replay_capacity`), with a checkpoint's copy, fit in the memory
  this machine has available;
- every stage spec of the chain of upstream stages composes (`stages.plan`), and `motion.joint_map`
  names bodies of the character;
- with `resume=true`, the run in run.json is still in the store, and a checkpoint in the run directory
  is complete, a weights file, written by this method, and fits this config's networks: its states are
  loaded into the method's components built here (for methods without upstream stages; those that have
  them are checked when the trainer restores). The newest that does is the one a resume starts from; an
  error only when none does.
"""

from __future__ import annotations

import json
import os
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from urllib.parse import urlsplit

import psutil
import torch

from orchestrator import checkpoint
from orchestrator.algos.base import method_class
from orchestrator.runtime.base import uses_ray, worker_gpus
from orchestrator.schema import Config, ConfigError
from orchestrator.tracking.identity import UNKNOWN, auth_header, experiment_access, server_url, whoami
from orchestrator.tracking.uri import redact, store_uri, tracking_uri_error
from orchestrator.world import load_character, load_library
from workers.body.character import Character, CharacterError
from workers.motion.errors import ClipError
from workers.replay.buffer import ReplayBuffer


class InputError(RuntimeError):
    """Input a run cannot use; the message is one line naming the file, key or address."""


def check(cfg: Config) -> None:
    """InputError (ConfigError for a config value) for the first input of `cfg` that a run cannot use."""
    if cfg.tracking.enabled and cfg.tracking.uri:
        problem = tracking_uri_error(cfg.tracking.uri)
        if problem:
            raise ConfigError(f"tracking.uri: {problem}")
        tracking_server(cfg.tracking.uri)
        own_experiment(cfg.tracking.uri, cfg.tracking.experiment or cfg.preset)
    learner_devices(cfg)
    sim_device(cfg)
    r = cfg.runtime
    if uses_ray(r) and r.address and (r.learner_gpus > 0 or r.worker_gpus > 0):
        cluster_gpus(cfg)  # a learner's or a rollout worker's share, whatever the simulator engine
    if cfg.algo.needs:
        from orchestrator.stages import plan  # loads mlflow: only for a method with upstream stages

        plan(cfg)  # every stage spec of the chain composes, before any stage trains
    character = character_and_clips(cfg)
    replay_memory(cfg, character)
    gpu_shares(cfg, character)
    if cfg.runtime.address and cfg.runtime._target_.endswith("RayRuntime"):
        from orchestrator.runtime.ray import AddressError, check_address

        try:
            check_address(cfg.runtime.address, cfg.runtime.connect_timeout_s)
        except AddressError as e:
            raise InputError(str(e)) from None
    if cfg.resume:
        resume_run(cfg)
        resume_checkpoint(cfg, character)


def tracking_server(uri: str, timeout_s: float = 3.0) -> None:
    """InputError when the MLflow server at `uri` (http or https) refuses this process's credentials
    (MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD, or none): every record would wait in the spool for
    ever. A server that does not answer is left to the tracker, which spools until it is back."""
    if urlsplit(uri).scheme not in ("http", "https"):
        return
    user = urlsplit(uri).username or os.environ.get("MLFLOW_TRACKING_USERNAME")
    headers = auth_header(uri)
    url = f"{server_url(uri)}/api/2.0/mlflow/experiments/search?max_results=1"
    try:
        urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout_s).close()
    except urllib.error.HTTPError as e:
        where = f"tracking.uri={redact(uri)}"
        if e.code == 401 and not headers:
            raise InputError(
                f"{where}: the server asks for a user: set MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD "
                '(for `make cluster-up`: eval "$(python -m orchestrator.cluster env)")'
            ) from None
        if e.code in (401, 403):
            raise InputError(
                f"{where}: the server refuses user {user!r} ({e.code}); check MLFLOW_TRACKING_PASSWORD"
            ) from None
    except (OSError, ValueError):
        return  # not answering (yet): the tracker spools


def own_experiment(uri: str, experiment: str) -> None:
    """InputError when the authenticated MLflow server at `uri` would refuse this user's run in `experiment`
    (PERMISSION_DENIED: another user made it, and it is only readable to this one), before anything trains."""
    who = whoami(uri)
    if who is None:
        return
    access = experiment_access(uri, who, experiment)
    if access.experiment_id is not None and not access.writable and access.permission != UNKNOWN:
        raise InputError(
            f"tracking.experiment={experiment!r}: user {who.user!r} may not create runs in it on {redact(uri)} "
            f"(the server gives {access.permission}; another user made it): name an experiment of your own, and "
            "this one in tracking.reuse_from to reuse its stages"
        )


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


def sim_device(cfg: Config) -> None:
    """ConfigError naming `sim.device` when the warp simulator is to run on a GPU this machine does not have
    (on a cluster, rollout workers see the GPUs Ray assigns them: not checked here)."""
    r = cfg.runtime
    here = not uses_ray(r) or not r.address
    if here and uses_ray(r) and r.worker_gpus > 0 and not torch.cuda.device_count():
        raise ConfigError(f"runtime.worker_gpus={r.worker_gpus:g}: no GPU on this machine (torch sees none)")
    if cfg.sim.backend != "warp" or not cfg.sim.device.startswith("cuda"):
        return
    if not here:
        if r.worker_gpus <= 0:
            raise ConfigError(
                f"sim.device={cfg.sim.device}: a rollout worker on the cluster at runtime.address sees only the GPUs "
                "Ray assigns it; set runtime.worker_gpus (e.g. 0.25)"
            )
        return
    index = int(cfg.sim.device.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise ConfigError(
            f"sim.device={cfg.sim.device}: no such GPU on this machine (torch {torch.__version__} sees "
            f"{torch.cuda.device_count()}); sim.device=cpu runs Warp's CPU kernels (slowly)"
        )
    if uses_ray(r) and index > 0:
        raise ConfigError(
            f"sim.device={cfg.sim.device}: under Ray a rollout worker sees only the GPU Ray gives it, as cuda:0; "
            "give sim.device=cuda (runtime=local runs on any GPU of this machine)"
        )
    warp_sees_gpus(cfg.sim.device)


def warp_sees_gpus(device: str) -> None:
    """ConfigError when Warp sees no CUDA device where torch does: warp-lang 1.19's binary is built with CUDA 13,
    which NVIDIA drivers before R580 do not run, and the run would fail late, inside the simulator."""
    import warp

    warp.config.quiet = True
    warp.init()
    if warp.get_cuda_device_count() == 0:
        raise ConfigError(
            f"sim.device={device}: Warp {warp.__version__} sees no CUDA device where torch sees "
            f"{torch.cuda.device_count()} (driver {_driver_version()}): its binary is built with CUDA 13, which needs "
            "an NVIDIA driver of R580 or newer; sim.backend=mujoco runs without it"
        )


def _driver_version() -> str:
    """The NVIDIA driver's version as nvidia-smi says it, else "unknown"."""
    import shutil
    import subprocess

    smi = shutil.which("nvidia-smi")
    if smi is None:
        return "unknown: no nvidia-smi"
    try:
        query = [smi, "--query-gpu=driver_version", "--format=csv,noheader"]
        out = subprocess.run(query, capture_output=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return out.stdout.decode().strip().splitlines()[0] if out.stdout.strip() else "unknown"


def gpu_shares(cfg: Config, character: Character) -> None:
    """ConfigError when the learners' GPUs as set (`runtime.learner_gpus`) leave the rollout workers' simulator on
    the GPU no share of one (`orchestrator.runtime.base.worker_gpus`), for a method whose learners are known
    before its upstream stages are."""
    cls = method_class(cfg)
    if cls.needs or not cls.uses_workers:
        return
    components = cls(cfg, character, None).components()  # descriptors only: nothing is built
    worker_gpus(cfg.runtime, cfg.sim, cfg.runtime.rollout_workers, sum(c.role != "replay" for c in components))


def cluster_gpus(cfg: Config) -> None:
    """ConfigError when a learner or a rollout worker asks for more GPUs than the Ray cluster at runtime.address
    has in all (Ray would wait for them without end), asked by connecting as a client, which starts nothing
    there. (Actors that each fit but not all together are refused when Ray is asked to reserve them,
    `RayRuntime.reserve`.)"""
    import ray

    from orchestrator.runtime.ray import AddressError, check_address

    r = cfg.runtime
    try:
        check_address(r.address, r.connect_timeout_s)
    except AddressError as e:
        raise InputError(str(e)) from None
    ray.init(address=r.address, log_to_driver=False, logging_level="ERROR")
    try:
        have = ray.cluster_resources().get("GPU", 0.0)
    finally:
        ray.shutdown()
    for key, asked in (("learner_gpus", r.learner_gpus), ("worker_gpus", r.worker_gpus)):
        if asked > have:
            raise ConfigError(
                f"runtime.{key}={asked:g}: the Ray cluster at runtime.address={r.address} has {have:g} GPU(s)"
            )


def replay_memory(cfg: Config, character: Character) -> None:
    """ConfigError when the method's replay buffers (`algo.loop.replay_capacity` transitions each), with the copy a
    checkpoint makes of them, would take more than this machine's available memory; not for a cluster's run
    (`runtime.address`), whose buffer lives on a node this process cannot see."""
    buffers = method_class(cfg).replay_buffers
    if not buffers or cfg.runtime.address:
        return
    capacity = cfg.algo.loop.replay_capacity
    per = buffers * ReplayBuffer.nbytes(1, character.num_bodies, character.num_actions)
    available = psutil.virtual_memory().available
    if 2 * capacity * per > available:
        gib = 2**30
        raise ConfigError(
            f"algo.loop.replay_capacity={capacity}: the replay buffer takes {capacity * per / gib:.1f} GiB and a "
            f"checkpoint copies it, {2 * capacity * per / gib:.1f} GiB in all, more than the {available / gib:.1f} "
            f"GiB this machine has available; at most {available // (2 * per):,} transitions fit"
        )


def character_and_clips(cfg: Config) -> Character:
    """The character and the motion library load (the library is built, and its clips cached, here), and
    `motion.joint_map` maps onto bodies the character has (whether or not a clip is a BVH file)."""
    try:
        character = load_character(cfg)
    except CharacterError as e:
        raise InputError(f"character.xml={cfg.character.xml}: {e.message}") from None
    for source, body in (cfg.motion.joint_map or {}).items():
        if body not in character.body_names:
            raise ConfigError(
                f"motion.joint_map.{source}: {body!r} is not a body of the character "
                f"(its bodies: {', '.join(character.body_names)})"
            )
    try:
        load_library(cfg, character)
    except ClipError as e:
        raise InputError(f"clip {e}") from None
    return character


def resume_run(cfg: Config) -> str | None:
    """The MLflow run a resume continues (run_dir/run.json), or None; InputError if the file is unreadable, or if
    it names a run that the store answers it does not have (deleted, or another store): continuing would make a
    new run without the params and config of the one it resumes."""
    path = Path(cfg.run_dir) / checkpoint.RUN_FILE
    if not path.exists():
        return None
    try:
        run_id = json.loads(path.read_text())["run_id"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, TypeError, KeyError):
        run_id = False
    if not (run_id is None or isinstance(run_id, str)):  # None: the run was not tracked
        raise InputError(f'{path}: not a run file ({{"run_id": "<MLflow run id>"}}); resume=true reads it')
    if run_id and cfg.tracking.enabled and missing_run(cfg, run_id):
        raise InputError(
            f"{path}: run {run_id} is not in the store {redact(store_uri(cfg.tracking.uri, cfg.run_dir))} "
            "(deleted, or another tracking.uri); resume=true would continue it. Give the store that has it, or "
            "move run.json aside to start a new run from the last checkpoint"
        )
    return run_id


def missing_run(cfg: Config, run_id: str) -> bool:
    """True when the run's store answers that it does not have `run_id` (False when it has it or does not answer)."""
    from orchestrator.tracking.query import run_exists  # loads mlflow: only when tracking

    return run_exists(store_uri(cfg.tracking.uri, cfg.run_dir), run_id) is False


def resume_checkpoint(cfg: Config, character: Character, log: Callable[[str], None] | None = None) -> Path | None:
    """The checkpoint a resume starts from: the newest in run_dir/checkpoints that loads into this config's
    components, each newer one that does not said in one line to `log`. InputError naming the file and what
    is wrong (for a size mismatch, the tensor and both shapes) when none does. The files are only read."""
    paths = checkpoint.newest_first(Path(cfg.run_dir) / "checkpoints")
    if not paths:
        return None
    method = method_class(cfg)(cfg, character, None)
    components = [] if method.needs else method.components()  # with upstream stages: built later, from them
    targets = None
    errors: list[checkpoint.CheckpointError] = []
    for path in paths:
        try:
            state = checkpoint.load(path)
            # The replay buffers are saved beside the checkpoint (the trainer refills them when they are not there).
            checkpoint.check_layout(path, state, [c.key for c in components if c.role != "replay"])
            if method.needs:  # its components fit or not once the trainer restores them
                return path
            try:
                checkpoint.LoopState(**state["loop"])
            except TypeError as e:
                raise checkpoint.CheckpointError(path, f"loop: {e}") from None
            if targets is None:  # built as the trainer builds them, without touching torch's threads or RNG
                threads = torch.get_num_threads()
                with torch.random.fork_rng(devices=[]):
                    targets = {c.key: c.cls(*c.args, **c.kwargs) for c in components if c.key in state}
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
