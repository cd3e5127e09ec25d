"""AMP (Peng et al. 2021): PPO on the reward of an adversarial motion prior.

Components: PPO (`learner-ppo`) and the discriminator (`learner-discriminator`)
with its replay of past policy transitions and the clips' transitions as data.
The workers record AMP's Φ(s) of every transition; the discriminator scores them
(style reward, Eq. 7) before its own update on them, and the mixed reward
r = w_G·r_G + w_S·r_S (Eq. 4) trains PPO. Episodes end on a fall (early
termination); there is no tracking termination, since AMP does not track the clip.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from orchestrator.algos.base import Component
from orchestrator.algos.onpolicy import OnPolicy, PPOAlgo
from orchestrator.components.amp import DiscriminatorActor
from orchestrator.schema import ConfigError
from workers.learners.discriminator import DiscriminatorConfig
from workers.recorders import AMPFeatures
from workers.sim.env import without_tracking_termination


@dataclass
class AMPConfig:
    # AMP's reward r = w_G·r_G + w_S·r_S (Eq. 4). Single-clip imitation (Sec. 8.4) trains on the style
    # reward alone: w_G = 0, w_S = 1. With a task, AMP uses w_G = w_S = 0.5.
    task_weight: float = 0.0
    style_weight: float = 1.0

    def __post_init__(self) -> None:
        for key in ("task_weight", "style_weight"):
            if getattr(self, key) < 0:
                raise ConfigError(f"algo.amp.{key} must be non-negative, got {getattr(self, key)}")


@dataclass
class AMPAlgo(PPOAlgo):
    discriminator: DiscriminatorConfig = field(default_factory=DiscriminatorConfig)
    amp: AMPConfig = field(default_factory=AMPConfig)


class AMP(OnPolicy):
    config_class = AMPAlgo
    observation = "state"

    def components(self) -> list[Component]:
        disc = Component("discriminator", DiscriminatorActor, (self.cfg,), actor="learner-discriminator")
        return super().components() + [disc]

    @classmethod
    def make_recorders(cls, cfg, character) -> list[AMPFeatures]:
        return [AMPFeatures(character)]

    @classmethod
    def sim_config(cls, cfg):
        return without_tracking_termination(super().sim_config(cfg), keep_time_limit=True)

    def rewards_and_updates(self, trainer, trajectories: list[Any]) -> tuple[Any, dict[str, Any]]:
        """The discriminator scores the trajectories (style reward, Eq. 7, mixed by Eq. 4), then learns from them."""
        disc, rt = trainer.handles["discriminator"], trainer.runtime
        rewards = rt.call(disc, "rewards", *trajectories)  # before the discriminator learns from them
        return rewards, {"discriminator": rt.call(disc, "train", *trajectories)}

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {**super().progress(metrics), "style": f"{metrics.get('disc/reward/style', float('nan')):.3g}"}
