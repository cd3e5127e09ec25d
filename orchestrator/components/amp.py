"""AMP's discriminator as a learner actor (`learner-discriminator`): the clip's transitions against the policy's.

It takes the rollout workers' trajectories as they are (object references on Ray), scores them with
the discriminator as it is (`rewards`: the style reward of AMP Eq. 7, mixed with a task reward by
Eq. 4: one small [T, M] array per worker, `workers.learners.discriminator.amp_reward`) and then learns from them
(`train`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orchestrator.components.base import LearnerActor, compiled, learner_device
from orchestrator.schema import Config
from orchestrator.world import load_character_and_library, seed_of
from workers.body.features import amp_dim
from workers.learners.discriminator import (
    DiscriminatorBatch,
    DiscriminatorLearner,
    amp_reward,
    policy_transitions,
    reference_transitions,
)
from workers.types import Trajectory


class DiscriminatorActor(LearnerActor):
    """AMP's discriminator: the clip's transitions against the policy's; rewards r = w_G·r_G + w_S·r_S."""

    def __init__(self, cfg: Config):
        super().__init__(cfg)
        character, library = load_character_and_library(cfg)
        self.config = cfg.algo.discriminator
        self.weights = cfg.algo.amp
        self.data = reference_transitions(character, library)
        self.learner = compiled(
            DiscriminatorLearner(amp_dim(character), self.config, seed_of(cfg, 6), learner_device(cfg)), cfg
        )
        self.rng = np.random.default_rng(seed_of(cfg, 7))
        self.last_rewards: dict[str, float] = {}

    def set_lr(self, lr: float) -> None:
        """Change the discriminator's step size (0 freezes it: the policy then trains on a fixed reward)."""
        for group in self.learner.optimizer.param_groups:
            group["lr"] = lr

    def rewards(self, *trajs: Trajectory) -> list[np.ndarray]:
        """The mixed reward [T, M] of each trajectory (AMP Eq. 4), from the discriminator as it is now; its terms'
        means are reported by the next `train` under reward/."""
        out, terms = [], []
        for tr in trajs:
            style = self.learner.reward(policy_transitions(tr)).reshape(tr.done.shape)
            reward, parts = amp_reward(style, tr.extras.get("task_reward"), self.weights.task_weight,
                                       self.weights.style_weight)  # fmt: skip
            out.append(reward)
            terms.append(parts)
        self.last_rewards = {f"reward/{k}": float(np.mean(np.concatenate([t[k] for t in terms]))) for k in terms[0]}
        return out

    def train(self, *trajs: Trajectory) -> dict[str, Any]:
        """Minibatches of the policy's transitions (shuffled) against as many reference transitions."""
        policy = np.concatenate([policy_transitions(tr) for tr in trajs])
        size = self.config.batch_size
        order = self.rng.permutation(len(policy))
        metrics = []
        for start in range(0, max(len(policy) - size + 1, 1), size):
            data = self.data[self.rng.integers(len(self.data), size=size)]
            metrics.append(self.learner.update(DiscriminatorBatch(data, policy[order[start : start + size]])))
        return {**self.report(metrics), **self.last_rewards}
