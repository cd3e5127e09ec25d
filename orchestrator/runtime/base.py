"""What a runtime offers the loop: spawn components, call their methods, wait, share objects.

The loop is written once against this interface; the backend is chosen when the
experiment is built. Components are plain classes; a handle refers to one, and
`call(handle, "method", ...)` returns a future that `get` resolves. Futures and
shared objects may be passed as arguments to other calls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from orchestrator.errors import ConfigError


@dataclass(frozen=True)
class Resources:
    cpus: float = 1.0
    gpus: float = 0.0
    max_restarts: int = 0
    cores: tuple[int, ...] = ()  # the CPU cores the actor runs on (`orchestrator.runtime.cores`); () any


class Runtime:
    name = "base"

    def reserve(self, bundles: list[Resources]) -> None:
        """Reserve every component's resources at once, in spawn order, before the first spawn."""

    def spawn(self, cls: type, *args: Any, name: str, resources: Resources | None = None, **kwargs: Any) -> Any:
        raise NotImplementedError

    def call(self, handle: Any, method: str, *args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError

    def get(self, futures: Any) -> Any:
        raise NotImplementedError

    def ready(self, futures: list[Any]) -> list[Any]:
        """The futures among these that have finished (all of them, locally)."""
        raise NotImplementedError

    def put(self, obj: Any) -> Any:
        """Share an object once; the result can be passed to many calls."""
        raise NotImplementedError

    def kill(self, handle: Any) -> None:
        """Kill a component as a crash would (tests of restarts)."""
        raise NotImplementedError

    def restarts(self, handle: Any) -> int:
        return 0

    def dashboard_url(self) -> str | None:
        return None

    def shutdown(self) -> None:
        pass


def uses_ray(runtime_cfg: Any) -> bool:
    return str(runtime_cfg._target_).endswith("RayRuntime")


def learner_gpus(runtime_cfg: Any, learners: int, gpu_workers: int = 0) -> float:
    """The GPUs each learner actor reserves under Ray: `runtime.learner_gpus` when it is set; with
    `learner_device` auto or cuda, a Ray started for the run (no `address`) and a GPU on this machine, an
    equal share of one GPU per learner (all learners on the first GPU), shared with `gpu_workers` rollout
    workers that simulate on it too (`worker_gpus`) and then with the driver (`driver_gpus`); else none."""
    r = runtime_cfg
    if not uses_ray(r) or r.learner_gpus > 0 or r.learner_device == "cpu" or r.address or learners < 1:
        return float(r.learner_gpus) if uses_ray(r) else 0.0
    return _share(learners + gpu_workers + (gpu_workers > 0))


def worker_gpus(runtime_cfg: Any, sim: Any, workers: int, learners: int) -> float:
    """The GPUs each rollout worker reserves under Ray: `runtime.worker_gpus` when it is set; with the warp
    simulator on a GPU (`sim.device` cuda), a Ray started for the run and a GPU here, an equal share of the
    first GPU with the learners that take one (`learner_gpus`) and the driver (`driver_gpus`); else none. Ray gives
    an actor without a GPU share no GPU to see, so a cuda simulator under Ray needs one."""
    r = runtime_cfg
    on_gpu = sim.backend == "warp" and sim.device.startswith("cuda")
    if not uses_ray(r) or r.worker_gpus > 0 or not on_gpu or r.address or workers < 1:
        return float(r.worker_gpus) if uses_ray(r) else 0.0
    if r.learner_gpus > 0 and r.learner_device != "cpu":  # the learners' GPUs as set; the workers share what is left
        import torch

        left = torch.cuda.device_count() - learners * r.learner_gpus
        if torch.cuda.device_count() > 0 and left <= 0:
            raise ConfigError(
                f"runtime.learner_gpus={r.learner_gpus} for {learners} learner(s) takes every GPU of this machine "
                f"({torch.cuda.device_count()}), leaving none to the rollout workers' simulator (sim.device="
                f"{sim.device}): lower it, or set runtime.worker_gpus"
            )
        return _share(workers + 1, min(left, 1.0))
    sharing = learners if r.learner_device != "cpu" else 0
    return _share(workers + 1 + sharing)


def driver_gpus(runtime_cfg: Any, sim: Any, workers: int, learners: int) -> float:
    """The share of the GPU that a Ray started for the run holds for the driver itself, which evaluates, renders and
    exports on the rollout workers' simulator (`orchestrator.world.evaluation_sim_config`: MuJoCo Warp on
    `sim.device`, a GPU it sees on this machine): a rollout worker's automatic share, so that Ray's accounting
    covers every process on the GPU. None where the workers' shares are set (`runtime.worker_gpus`: the setter's
    accounting) or the cluster is another's (`runtime.address`: its driver may have no GPU, and evaluates on Warp's
    CPU device then)."""
    if runtime_cfg.worker_gpus > 0:
        return 0.0
    return worker_gpus(runtime_cfg, sim, workers, learners)


def _share(actors: int, gpus: float = 1.0) -> float:
    """Each of `actors` actors' equal share of `gpus` GPUs (at most one: Ray puts fractions on one GPU), rounded
    down to Ray's 1e-4, so that the shares never add up to more than there is."""
    import torch

    if torch.cuda.device_count() == 0 or actors < 1:
        return 0.0
    return math.floor(gpus * 10_000 / actors) / 10_000
