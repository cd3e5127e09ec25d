"""ControlVAE's learner actors: the world model (`learner-world_model`) and the VAE (`learner-vae`), on replay data."""

from __future__ import annotations

from typing import Any

from orchestrator.components.base import LearnerActor, compiled, learner_device
from orchestrator.schema import Config
from orchestrator.world import load_character_and_library, seed_of
from workers.learners.base import Weights
from workers.learners.vae import VAEBatch, VAELearner
from workers.learners.world_model import WorldModelBatch, WorldModelLearner, build_world_model
from workers.models import body_state
from workers.types import StartBatch, WindowBatch


class WorldModelActor(LearnerActor):
    def __init__(self, cfg: Config, num_bodies: int, action_dim: int):
        super().__init__(cfg, seed_offset=2)
        dt = 1.0 / cfg.character.control_hz
        self.learner = compiled(
            WorldModelLearner(num_bodies, action_dim, dt, cfg.algo.world_model, learner_device(cfg)), cfg
        )

    def train(self, batches: list[WindowBatch]) -> dict[str, Any]:
        return self.report([self.learner.update(WorldModelBatch(b.states, b.actions)) for b in batches])


class VAEActor(LearnerActor):
    """The VAE learner with a frozen copy of the world model and the library it draws references from."""

    def __init__(self, cfg: Config, num_bodies: int, action_dim: int):
        super().__init__(cfg, seed_offset=3)
        _, self.library = load_character_and_library(cfg)
        wm = cfg.algo.world_model
        world_model = build_world_model(num_bodies, action_dim, wm, 1.0 / cfg.character.control_hz)
        self.learner = compiled(
            VAELearner(num_bodies, action_dim, cfg.algo.vae, world_model, seed_of(cfg, 4), learner_device(cfg)), cfg
        )
        self.world_model_version = -1

    def set_world_model_weights(self, weights: Weights) -> int:
        self.learner.set_world_model_weights(weights)
        self.world_model_version = weights.version
        return weights.version

    def train(self, batches: list[WindowBatch] | list[StartBatch]) -> dict[str, Any]:
        """One update per batch: each window's first state (or each single state) starts a synthetic
        rollout that tracks the reference clip following its frame."""
        steps = self.learner.config.rollout_steps
        metrics = []
        for b in batches:
            reference = body_state.reference_windows(self.library, b.clip_id, b.frame, steps)
            if isinstance(b, StartBatch):
                batch = VAEBatch(b.states[:, None], reference, norm_states=b.norm_states)
            else:
                batch = VAEBatch(b.states, reference)
            metrics.append(self.learner.update(batch))
        return {**self.report(metrics), "world_model_version": float(self.world_model_version)}

    def state_dict(self) -> dict[str, Any]:
        return {"learner": self.learner.state_dict(), "world_model": self.learner.world_model.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state["learner"])
        self.learner.world_model.load_state_dict(state["world_model"])
