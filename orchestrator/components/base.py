"""What every component shares: the learner actors' common surface, and how a component tells its lives apart.

Components are the stateful parts of a method (learners, a replay buffer) and the rollout workers, as
plain classes that build what they need from the validated config inside whatever process hosts them
(this one, or a Ray actor) and expose coarse methods: a rollout worker collects hundreds of steps per
call, a learner takes a list of batches per call. None of them knows where it runs. One module per
method holds its own (`controlvae`, `physicsvae`, `pulse`, `amp`, `task`; `ppo` is shared by the PPO
methods); `rollout` and `replay` serve every method.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

import numpy as np
import torch

from orchestrator.schema import Config
from orchestrator.world import seed_of
from workers.learners.base import Learner, Weights, resolve_device

log = logging.getLogger(__name__)


def mean_metrics(metrics: list[dict[str, float]]) -> dict[str, float]:
    if not metrics:
        return {}
    keys = metrics[-1].keys()
    out = {k: float(np.mean([m[k] for m in metrics if k in m])) for k in keys}
    out["updates"] = float(len(metrics))
    return out


def incarnation() -> str:
    """Tells one life of a component from the next: a restarted Ray actor is a new process."""
    return f"{os.getpid()}-{time.time_ns()}"


def learner_device(cfg: Any) -> Any:
    """The torch device this process's learner computes on (`runtime.learner_device`, resolved here: a Ray
    actor sees the GPUs Ray assigned it)."""
    return resolve_device(cfg.runtime.learner_device)


def compiled(learner: Learner, cfg: Any) -> Learner:
    """The learner with its loss through `torch.compile` as `runtime.learner_compile` says (eager: as it is;
    default; reduce-overhead: CUDA graphs on a GPU). A loss that takes a gradient of a gradient (the AMP
    discriminator's penalty) stays eager, which the log says once per actor."""
    mode = cfg.runtime.learner_compile
    if mode == "eager":
        return learner
    if learner.double_backward:
        log.info(
            "%s: its loss stays eager (runtime.learner_compile=%s cannot take its gradient penalty)", learner.name, mode
        )
        return learner
    learner.compile(None if mode == "default" else mode)
    return learner


def actor_preamble(cfg: Config, seed_offset: int | None = None) -> None:
    """What every actor does first, in whatever process hosts it: torch's threads as `runtime.torch_threads`, and,
    for an actor whose networks draw their first weights from torch's global generator, that generator seeded for
    its part of the run (`seed_of(cfg, seed_offset)`)."""
    torch.set_num_threads(cfg.runtime.torch_threads)
    if seed_offset is not None:
        torch.manual_seed(seed_of(cfg, seed_offset))


class LearnerActor:
    """What every method's learner actors share: weights, checkpoints, and the report every `train` returns."""

    learner: Learner

    def __init__(self, cfg: Config, seed_offset: int | None = None) -> None:
        self.incarnation = incarnation()
        actor_preamble(cfg, seed_offset)

    def report(self, metrics: list[dict[str, float]]) -> dict[str, Any]:
        """Mean metrics of the updates, the weights' version, and this actor's incarnation."""
        out: dict[str, Any] = mean_metrics(metrics)
        out["version"] = float(self.learner.version)
        out["incarnation"] = self.incarnation
        return out

    def get_weights(self) -> Weights:
        return self.learner.get_weights()

    def state_dict(self) -> dict[str, Any]:
        return self.learner.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state)
