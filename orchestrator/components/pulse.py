"""PULSE's distillation learner (`learner-vae` of `algo=pulse`): the student learns from the teacher's labels.

The replay holds the student's own trajectories; each update takes windows of T
consecutive states from it, has the teacher (the upstream tracking expert, a PPO
actor-critic) label every state with its deterministic action (`workers.distill`),
and takes one step of PULSE's Eq. 3 on them: ‖a_teacher − a‖² + λ·L_regu + β·KL(E ‖ R).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orchestrator.components.base import LearnerActor, compiled, learner_device
from orchestrator.schema import Config
from orchestrator.upstream import Upstream, expert_weights
from orchestrator.world import load_character_and_library, seed_of
from workers.distill import teacher_actions
from workers.learners.vae import VAEBatch, VAELearner
from workers.models import body_state
from workers.policies import expert_module
from workers.types import WindowBatch


class PulseActor(LearnerActor):
    def __init__(self, cfg: Config, num_bodies: int, action_dim: int, expert: Upstream):
        super().__init__(cfg, seed_offset=3)
        self.character, self.library = load_character_and_library(cfg)
        t = expert_weights(expert).state  # downloaded here: a restarted actor needs nothing from the driver
        self.teacher = expert_module(t, num_bodies, action_dim)
        self.residual, self.observation = bool(t["residual"]), str(t["observation"])
        self.learner = compiled(
            VAELearner(num_bodies, action_dim, cfg.algo.vae, seed=seed_of(cfg, 4), device=learner_device(cfg)), cfg
        )

    def labels(self, states: np.ndarray, clip_id: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """The teacher's actions [N, T, A] for states [N, T, B, 13] at (clip, frame) [N, T]."""
        n, steps = clip_id.shape
        flat = teacher_actions(
            self.teacher,
            self.character,
            self.library,
            states.reshape(n * steps, *states.shape[2:]),
            clip_id.reshape(-1),
            frame.reshape(-1),
            self.residual,
            self.observation,
        )
        return flat.reshape(n, steps, -1)

    def batch(self, b: WindowBatch) -> VAEBatch:
        steps = b.actions.shape[1]
        frames = b.frame[:, None] + np.arange(steps)
        clips = np.repeat(b.clip_id[:, None], steps, axis=1)
        reference = body_state.reference_windows(self.library, b.clip_id, b.frame, steps)
        return VAEBatch(b.states, reference, self.labels(b.states[:, :-1], clips, frames))

    def train(self, batches: list[WindowBatch]) -> dict[str, Any]:
        return self.report([self.learner.update(self.batch(b)) for b in batches])
