"""The plug-in contract: what a method declares (`Method`, `Component`) and may call on the trainer (`TrainerAPI`).

A method (`conf/algo/<name>.yaml` names its class with `_target_`; one module per method in this
folder, named by its paper) says:

- its config (`config_class`): a dataclass beside the method, `orchestrator.schema.MethodConfig` with the
  method's sections and its loop, which conf/algo/<name>.yaml is validated against (a key the method does
  not have is refused, named);
- which upstream stages it reads (`needs`), and whether a finished run of it can serve as an
  expert (`expert`);
- which stateful components it runs (`components`: learners, a replay buffer; classes of
  `orchestrator.components`), built by the shared trainer through the runtime, checkpointed, and
  reloaded from the last checkpoint when Ray restarts one;
- what its rollout workers run (`make_policy`, `make_recorders`, `sim_config`, `worker_options`):
  every method uses the one `workers.rollout.RolloutWorker`;
- its iteration (`step`): sample → add to replay or hand to the learners → update → publish
  weights; it returns the samples it collected and its metrics;
- its evaluation (`evaluate`), by the protocol of its paper.

The trainer (`orchestrator.trainer.Trainer`) owns everything else: the iteration budget, the
progress bar, checkpoint and evaluation cadence, recovery, metrics and resume. `TrainerAPI` below
is all of it that a method may use.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from orchestrator.compose import find_method
from orchestrator.schema import Config, MethodConfig
from orchestrator.upstream import Upstream
from orchestrator.world import collection_sim_config, load_character_and_library

if TYPE_CHECKING:
    from orchestrator.runtime.base import Runtime
    from orchestrator.tracking.base import RunLogger
    from workers.body.character import Character
    from workers.learners.base import Weights
    from workers.motion.library import MotionLibrary
    from workers.policies import Policy
    from workers.recorders import Recorder
    from workers.sim.env import SimConfig


class TrainerState(Protocol):
    iteration: int  # iterations done
    samples: int  # environment transitions collected (the metrics' step)


class TrainerAPI(Protocol):
    """What a method may use of the trainer that runs it (`orchestrator.trainer.Trainer` implements it)."""

    cfg: Config
    runtime: Runtime  # calls components and workers: `runtime.call(handle, "method", ...)`, `runtime.get(future)`
    logger: RunLogger  # the run's metrics and artifacts (MLflow, or nothing)
    handles: dict[str, Any]  # the method's components, by `Component.key`
    workers: list[Any]  # the rollout workers' handles
    state: TrainerState
    weights_version: int  # the newest published policy weights' version (-1: none yet)
    weights_ref: Any  # those weights in the object store (None: none yet)

    def publish(self, weights: Weights) -> None:
        """The policy's weights into the object store, once per version (never non-finite ones)."""

    def collect(self, steps: int, staleness: int) -> list[Any]:
        """One collect call per worker, refreshed first when more than `staleness` versions behind; futures."""

    def configure_workers(self, **settings: Any) -> None:
        """Settings every rollout worker gets before its next collect (`RolloutActor.configure`)."""

    def check_alive(self, key: str, incarnation: str) -> None:
        """Reload component `key` from the last checkpoint if it reports a new life (Ray restarted it)."""

    def worker_came_back(self, w: int, version: int) -> None:
        """Worker `w` reported weights older than it was sent: it restarted and is refreshed."""

    def took_collections(self, key: str, infos: list[dict[str, Any]]) -> None:
        """Component `key` took one collection per worker (summaries with `incarnation` and `version`)."""

    def worker_restarts(self) -> int:
        """Restarts of the rollout workers so far."""


@dataclass
class Component:
    """A stateful component of a method: its checkpoint key, class, constructor arguments and actor name."""

    key: str  # key in checkpoints and in `Trainer.handles` ("world_model", "replay", ...)
    cls: type
    args: tuple = ()
    actor: str = ""  # the Ray actor's name ("learner-world_model"); defaults to the key
    role: str = "learner"  # "learner" or "replay": which resources it gets
    own_core: bool = False  # the loop waits on it: a core of its own under runtime.pin_cores=auto
    kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.actor = self.actor or self.key


class Method:
    """The base of every method. Subclasses set `config_class` and implement the hooks below."""

    # The method's config: `algo`'s schema (its sections and its loop, `orchestrator.schema.sections_of`).
    config_class: type[MethodConfig] = MethodConfig
    # The roles of the upstream stages it reads (`algo.needs`, orchestrator/stages.py).
    needs: tuple[str, ...] = ()
    # Whether the Trainer starts rollout workers for it (offline methods train on a dataset).
    uses_workers: bool = True
    # What kind of expert a finished run of this method is for the stages that distil one (demos, PULSE):
    # "ppo" (its PPO actor), "vae" (its VAE controller's posterior) or None (it cannot be one).
    expert: str | None = None
    # Replay buffers of `algo.loop.replay_capacity` transitions it holds in memory (checked against the machine's
    # memory before a run starts: `orchestrator.preflight.replay_memory`).
    replay_buffers: int = 0

    def __init__(self, cfg: Config, character: Character, upstream: dict[str, Upstream] | None = None):
        self.cfg = cfg
        self.character = character
        self.upstream = dict(upstream or {})
        self._loaded: tuple[Character, MotionLibrary] | None = None

    @classmethod
    def variant(cls, cfg: Config) -> type[Method]:
        """The class that runs `cfg`, where a setting of the method picks another loop (the task policy's
        `algo.task.trainer=ppo`: PPO's); this class by default."""
        return cls

    @classmethod
    def check_config(cls, algo: MethodConfig) -> None:
        """A rule between the method's own sections that no one section can check alone; raises ConfigError
        naming the key (`compose.validate` calls it). None by default."""

    @classmethod
    def needs_of(cls, cfg: Config) -> dict[str, str]:
        """Role → spec of the upstream stages a run of `cfg` reads: `algo.needs` as it is, unless a method
        expands it (the demos stage: one expert per clip)."""
        return dict(cfg.algo.needs)

    def character_and_library(self) -> tuple[Character, MotionLibrary]:
        """This process's own character and motion library, loaded when first asked (for evaluation and
        data balancing on the driver; every component loads its own)."""
        if self._loaded is None:
            self._loaded = load_character_and_library(self.cfg)
        return self._loaded

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
        return collection_sim_config(cfg)

    # The iteration -----------------------------------------------------------------
    def start(self, trainer: TrainerAPI) -> None:
        """Before the first step (and after a resume): publish weights, launch collection."""

    def step(self, trainer: TrainerAPI) -> tuple[int, dict[str, float]]:
        """One iteration; (environment samples collected, metrics)."""
        raise NotImplementedError

    def finish(self, trainer: TrainerAPI) -> None:
        """After the last step, before the final evaluation and checkpoint."""

    def evaluate(self, trainer: TrainerAPI, final: bool) -> dict[str, float]:
        return {}

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        """What the progress bar shows beside the sample count."""
        return {}

    def policy_weights(self, trainer: TrainerAPI) -> Weights | None:
        """The weights of the policy `make_policy` builds, exported as the run's model at its end
        (orchestrator/tracking/model.py); by default the last published, None when nothing was."""
        return trainer.runtime.get(trainer.weights_ref) if trainer.weights_ref is not None else None

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
    def of(cls, cfg: Config, learner: str, ratio: float | None = None) -> UpdateSchedule:
        """The schedule of `algo.<learner>` (its batch_size and rollout_steps) at `ratio`, by default
        `algo.loop.replay_ratio`."""
        section = getattr(cfg.algo, learner)
        return cls(cfg.algo.loop.replay_ratio if ratio is None else ratio, section.batch_size, section.rollout_steps)

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


class ReplayFed(Method):
    """A method whose workers' collections go straight into one of its components (a replay buffer, or
    the task learner's goal buffer) while its learners update: ControlVAE, PULSE, the model-based task.

    Collection is pipelined: the collect calls issued last iteration hand their trajectories to
    that component directly (only summaries come back) and the next calls are issued at once, so
    that on Ray the workers collect while the learners update; locally the same calls run in order."""

    def __init__(self, cfg: Config, character: Character, upstream: dict[str, Upstream] | None = None):
        super().__init__(cfg, character, upstream)
        self.pending: list[Any] = []  # the collect calls in flight

    def publish(self, trainer: TrainerAPI) -> None:
        """The policy's newest weights to the workers (by default those of the `vae` learner)."""
        raise NotImplementedError

    def start(self, trainer: TrainerAPI) -> None:
        self.publish(trainer)
        self.pending = trainer.collect(self.cfg.algo.loop.collect_steps, self.cfg.algo.loop.staleness)

    def exchange(self, trainer: TrainerAPI, key: str) -> tuple[list[dict[str, Any]], int]:
        """Last iteration's collections into component `key` (`add_trajectory`), the next ones issued;
        (each worker's summary, the transitions collected)."""
        rt = trainer.runtime
        infos = rt.get([rt.call(trainer.handles[key], "add_trajectory", f) for f in self.pending])
        trainer.took_collections(key, infos)
        self.pending = trainer.collect(self.cfg.algo.loop.collect_steps, self.cfg.algo.loop.staleness)
        return infos, sum(i["transitions"] for i in infos)

    def finish(self, trainer: TrainerAPI) -> None:
        trainer.runtime.get(self.pending)  # let the last collection finish before the final checkpoint


def method_class(cfg: Config) -> type[Method]:
    """The method class that runs `cfg`: the one `algo._target_` names, or the variant it picks for this config
    (`Method.variant`)."""
    cls = find_method(cfg.algo._target_)
    if not issubclass(cls, Method):
        raise TypeError(f"{cfg.algo._target_} is not a method (a subclass of orchestrator.algos.base.Method)")
    return cls.variant(cfg)
