"""Methods as plug-ins: each module here declares a method's components and its iteration step.

A method (`conf/algo/<name>.yaml` names its class with `_target_`) says:

- which config sections of `algo` it uses (`sections`); `schema.validate` refuses a
  section the method does not have, with its key named;
- which stateful components it runs (`components`: learners, a replay buffer),
  built by the shared `Trainer` through the runtime, checkpointed, and reloaded
  from the last checkpoint when Ray restarts one;
- what its rollout workers run (`make_policy`, `make_recorders`, `sim_config`, `worker_options`):
  every method uses the one `workers.rollout.RolloutWorker`;
- its iteration (`step`): sample → add to replay or hand to the learners →
  update → publish weights; it returns the samples it collected and its metrics;
- its evaluation (`evaluate`), by the protocol of its paper.

The `Trainer` (`orchestrator.loop`) owns everything else: the iteration budget, the
progress bar, checkpoint and evaluation cadence, recovery, metrics and resume.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from orchestrator.runtime.base import Resources

if TYPE_CHECKING:
    from orchestrator.loop import Trainer
    from orchestrator.schema import Config
    from orchestrator.stages import Upstream
    from workers.learners.base import Weights
    from workers.policies import Policy
    from workers.recorders import Recorder
    from workers.sim.character import Character
    from workers.sim.env import SimConfig


@dataclass
class Component:
    """A stateful component of a method: its checkpoint key, class, constructor arguments and actor name."""

    key: str  # key in checkpoints and in `Trainer.handles` ("world_model", "replay", ...)
    cls: type
    args: tuple = ()
    actor: str = ""  # the Ray actor's name ("learner-world_model"); defaults to the key
    role: str = "learner"  # "learner" or "replay": which resources it gets
    kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.actor = self.actor or self.key


class Method:
    """The base of every method. Subclasses set `sections` and implement the hooks below."""

    # The config sections of `algo` this method uses, besides `loop` (which every method has).
    sections: tuple[str, ...] = ()
    # The roles of the upstream stages it reads (`algo.needs`, orchestrator/stages.py).
    needs: tuple[str, ...] = ()
    # Whether the Trainer starts rollout workers for it (offline methods train on a dataset).
    uses_workers: bool = True

    def __init__(self, cfg: Config, character: Character, upstream: dict[str, Upstream] | None = None):
        self.cfg = cfg
        self.character = character
        self.upstream = dict(upstream or {})

    # What runs where -------------------------------------------------------------
    def components(self) -> list[Component]:
        raise NotImplementedError

    @classmethod
    def make_policy(cls, cfg: Config, character: Character) -> Policy:
        """The policy a rollout worker runs (built inside the worker's process)."""
        raise NotImplementedError

    @classmethod
    def make_recorders(cls, cfg: Config, character: Character) -> list[Recorder]:
        """What the rollout workers record beyond states, actions and the policy's extras."""
        return []

    @classmethod
    def worker_options(cls, cfg: Config) -> dict[str, Any]:
        """Further keyword arguments of the rollout workers (`workers.rollout.RolloutWorker`)."""
        return {}

    @classmethod
    def sim_config(cls, cfg: Config) -> SimConfig:
        """The simulator as the rollout workers run it (rates and termination rules)."""
        from orchestrator.components import collection_sim_config

        return collection_sim_config(cfg)

    # The iteration -----------------------------------------------------------------
    def start(self, t: Trainer) -> None:
        """Before the first step (and after a resume): publish weights, launch collection."""

    def step(self, t: Trainer) -> tuple[int, dict[str, float]]:
        """One iteration; (environment samples collected, metrics)."""
        raise NotImplementedError

    def finish(self, t: Trainer) -> None:
        """After the last step, before the final evaluation and checkpoint."""

    def evaluate(self, t: Trainer, final: bool) -> dict[str, float]:
        return {}

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        """What the progress bar shows beside the sample count."""
        return {}

    def policy_weights(self, t: Trainer) -> Weights | None:
        """The weights of the policy `make_policy` builds, exported as the run's model at its end
        (orchestrator/tracking/model.py); by default the last published, None when nothing was."""
        return t.rt.get(t.weights_ref) if t.weights_ref is not None else None

    # The method's own counters, in checkpoints ------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass


class UpdateSchedule:
    """A learner's updates by its replay ratio: `ratio` learner samples (transitions in rollouts) per collected
    sample, an update taking `batch · length` of them; the fraction of an update not yet due carries over."""

    def __init__(self, ratio: float, batch: int, length: int):
        self.per_sample = ratio / (batch * length)
        self.credit = 0.0
        self.updates = 0

    @classmethod
    def of(cls, cfg: Config, learner: str) -> UpdateSchedule:
        """The schedule of `algo.<learner>` (its batch_size and rollout_steps) at its replay ratio:
        `algo.loop.replay_ratios[learner]`, else `algo.loop.replay_ratio`."""
        loop, section = cfg.algo.loop, getattr(cfg.algo, learner)
        return cls(loop.replay_ratios.get(learner, loop.replay_ratio), section.batch_size, section.rollout_steps)

    def due(self, collected: int) -> int:
        """The updates the `collected` new samples make due (counted in `updates`)."""
        credit = self.credit + self.per_sample * collected
        n = int(credit)
        self.credit = credit - n
        self.updates += n
        return n

    def state_dict(self, key: str) -> dict[str, float | int]:
        return {f"{key}_credit": self.credit, f"{key}_updates": self.updates}

    def load_state_dict(self, state: dict[str, Any], key: str) -> None:
        self.credit = float(state[f"{key}_credit"])
        self.updates = int(state[f"{key}_updates"])


def method_class(target: str) -> type[Method]:
    """The method class named by `algo._target_`."""
    module, _, name = target.rpartition(".")
    cls = getattr(importlib.import_module(module), name, None) if module else None
    if not (isinstance(cls, type) and issubclass(cls, Method)):
        raise TypeError(f"{target} is not a method (a subclass of orchestrator.algos.Method)")
    return cls


def learner_resources(cfg: Config) -> Resources:
    r = cfg.runtime
    return Resources(cpus=r.learner_cpus, gpus=r.learner_gpus, max_restarts=r.max_restarts)
