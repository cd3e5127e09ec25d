"""PhysicsVAE (Won et al. 2022) in two offline stages on the expert's demos.

`algo=simulation_layer`: the simulation layer, the world model trained on the demos'
(state, action) windows, then frozen (PhysicsVAE trains it first, 300 epochs).
`algo=physicsvae`: the conditional VAE on the demos' transitions by Eq. 1, behaviour
cloning + α·simulation consistency through the frozen layer + β·KL to N(0, I)
(600 epochs). Both need the `demos` stage; PhysicsVAE also the `world_model` stage, so
that every point of an α sweep shares one expert, one dataset and one layer.

One iteration is one epoch (`orchestrator.components.physicsvae`). Both report the expert's quality
from the demos' manifest (`expert/...`) in their run. Evaluation: the layer's held-out
prediction error; the VAE's held-out errors and time-until-fall by PhysicsVAE's protocol
(z ~ N(0, I) every control step, `eval.fall_rollouts` rollouts from one fixed start,
capped at `eval.fall_max_seconds`), with the tracking error of the posterior.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from orchestrator.algos.base import Component, Method
from orchestrator.components.physicsvae import PhysicsVAEActor, SimulationLayerActor
from orchestrator.evaluation.protocols import evaluate_controller
from orchestrator.schema import ConfigError, MethodConfig
from orchestrator.upstream import load_manifest
from workers.learners.vae import PhysicsVAEObjective
from workers.learners.world_model import WorldModelConfig
from workers.policies import VAEPolicy


@dataclass
class OfflineConfig:
    # Offline training on a demos dataset (the simulation_layer and physicsvae stages): one iteration is one
    # epoch, a pass over the training transitions. PhysicsVAE: the learning rate decays x0.7 every 50 epochs.
    lr_decay: float = 0.7
    decay_every: int = 50
    # Rollouts of each clip held out of training (the last ones) for the held-out metrics.
    holdout_rollouts: int = 1
    # The updates' arithmetic: "float32", or "bfloat16" (torch.autocast: the matmuls in bfloat16, the weights,
    # the optimiser and the losses' sums in float32; 1.6x an update on a CPU with bfloat16 GEMMs). It changes the
    # numbers, so it is part of the stage's hash, and it ships only where a paired study shows that it does not
    # change what the stages learn (docs/physicsvae.md).
    precision: str = "float32"

    def __post_init__(self) -> None:
        if self.precision not in ("float32", "bfloat16"):
            raise ConfigError(f"algo.offline.precision: expected 'float32' or 'bfloat16', got {self.precision!r}")
        if not 0 < self.lr_decay <= 1:
            raise ConfigError(f"algo.offline.lr_decay must be in (0, 1], got {self.lr_decay}")
        if self.decay_every < 1 or self.holdout_rollouts < 0:
            raise ConfigError("algo.offline.decay_every must be at least 1 and holdout_rollouts non-negative")


@dataclass
class SimulationLayerAlgo(MethodConfig):
    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    offline: OfflineConfig = field(default_factory=OfflineConfig)


@dataclass
class PhysicsVAEAlgo(MethodConfig):
    vae: PhysicsVAEObjective = field(default_factory=PhysicsVAEObjective)  # the layer: its world_model stage's
    offline: OfflineConfig = field(default_factory=OfflineConfig)


class Offline(Method):
    """What both offline stages (the simulation layer and the VAE) share: the demos, an epoch per iteration,
    held-out metrics."""

    uses_workers = False
    learner_key = ""

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        # The learner actor downloads the demos itself; here only the manifest, checked up front.
        self.manifest = load_manifest(self.upstream["demos"]) if "demos" in self.upstream else {}

    def start(self, trainer) -> None:
        if trainer.state.iteration == 0:
            trainer.logger.log_metrics(self.expert_metrics(), step=0)

    def expert_metrics(self) -> dict[str, float]:
        """The expert's quality, as recorded in the demos' manifest: it bounds what is learnt from them."""
        out = {f"expert/{k}": float(v) for k, v in self.manifest.get("expert", {}).items()}
        out.update({f"demos/{k}": float(v) for k, v in self.manifest.get("counts", {}).items()})
        return out

    def step(self, trainer) -> tuple[int, dict[str, float]]:
        rt, key = trainer.runtime, self.learner_key
        m = rt.get(rt.call(trainer.handles[key], "train_epoch"))
        trainer.check_alive(key, m.pop("incarnation"))
        return int(m["updates"] * self.batch_size()), {f"{key}/{k}": float(v) for k, v in m.items()}

    def batch_size(self) -> int:
        raise NotImplementedError

    def heldout(self, trainer) -> dict[str, float]:
        rt = trainer.runtime
        m = rt.get(rt.call(trainer.handles[self.learner_key], "validate"))
        return {f"eval/{k}": float(v) for k, v in m.items()}

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"loss": f"{metrics.get(f'{self.learner_key}/loss', float('nan')):.3g}"}


class SimulationLayer(Offline):
    config_class = SimulationLayerAlgo
    needs = ("demos",)
    learner_key = "world_model"

    def components(self) -> list[Component]:
        b, a = self.character.num_bodies, self.character.num_actions
        args = (self.cfg, self.upstream["demos"], b, a)
        return [Component("world_model", SimulationLayerActor, args, actor="learner-world_model")]

    def batch_size(self) -> int:
        return self.cfg.algo.world_model.batch_size

    def evaluate(self, trainer, final: bool) -> dict[str, float]:
        return self.heldout(trainer)


class PhysicsVAE(Offline):
    config_class = PhysicsVAEAlgo
    needs = ("demos", "world_model")
    learner_key = "vae"

    def components(self) -> list[Component]:
        b, a = self.character.num_bodies, self.character.num_actions
        args = (self.cfg, self.upstream["demos"], b, a, self.upstream["world_model"])
        return [Component("vae", PhysicsVAEActor, args, actor="learner-vae")]

    def batch_size(self) -> int:
        return self.cfg.algo.vae.batch_size

    @classmethod
    def make_policy(cls, cfg, character) -> VAEPolicy:
        """Not run by workers (the method is offline): the form its controller is exported in."""
        return VAEPolicy(character.num_bodies, character.num_actions, cfg.algo.vae)

    def policy_weights(self, trainer):
        return trainer.runtime.get(trainer.runtime.call(trainer.handles["vae"], "get_weights"))

    def evaluate(self, trainer, final: bool) -> dict[str, float]:
        weights = self.policy_weights(trainer)
        metrics = self.heldout(trainer)
        metrics.update(
            evaluate_controller(
                self.cfg, *self.character_and_library(), weights, trainer.logger, trainer.state.iteration, final
            )
        )
        return metrics
