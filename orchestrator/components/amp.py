"""AMP's discriminator as a learner actor (`learner-discriminator`): the clip's transitions against the policy's.

It takes the rollout workers' trajectories as they are (object references on Ray), scores them with
the discriminator as it is (`rewards`: the style reward of AMP Eq. 7, mixed with a task reward by
Eq. 4: one small [T, M] array per worker) and then learns from them (`train`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orchestrator.components.base import LearnerActor, compiled, learner_device
from orchestrator.schema import Config
from orchestrator.world import load_character_and_library, seed_of
from workers.body.character import Character
from workers.body.features import amp_dim, amp_features
from workers.learners.discriminator import DiscriminatorBatch, DiscriminatorLearner
from workers.motion.library import MotionLibrary
from workers.types import Trajectory


def reference_transitions(character: Character, library: MotionLibrary) -> np.ndarray:
    """Every consecutive pair of reference frames as (Φ(s), Φ(s')) [N, 2·amp_dim] (looping clips wrap)."""
    clips, frames = [], []
    for c, n in enumerate(library.num_frames):
        last = n if library.loop[c] else n - 1
        clips.append(np.full(last, c))
        frames.append(np.arange(last))
    clip, frame = np.concatenate(clips), np.concatenate(frames)
    before = amp_features(character, library.state(clip, frame))
    after = amp_features(character, library.state(clip, frame + 1))
    return np.concatenate((before, after), axis=1)


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

    @staticmethod
    def transitions(tr: Trajectory) -> np.ndarray:
        """(Φ(s), Φ(s')) [T·M, 2·amp_dim] of a trajectory, time-major."""
        before, after = tr.extras["amp_obs"], tr.extras["amp_next_obs"]
        return np.concatenate((before, after), axis=-1).reshape(-1, 2 * before.shape[-1])

    def rewards(self, *trajs: Trajectory) -> list[np.ndarray]:
        """The mixed reward [T, M] of each trajectory, from the discriminator as it is now."""
        out, style_all = [], []
        for tr in trajs:
            style = self.learner.reward(self.transitions(tr)).reshape(tr.done.shape)
            task = tr.extras.get("task_reward", np.zeros_like(style))
            out.append((self.weights.task_weight * task + self.weights.style_weight * style).astype(np.float32))
            style_all.append(style)
        self.last_rewards = {"style_reward": float(np.mean(np.concatenate(style_all)))}
        return out

    def train(self, *trajs: Trajectory) -> dict[str, Any]:
        """Minibatches of the policy's transitions (shuffled) against as many reference transitions."""
        policy = np.concatenate([self.transitions(tr) for tr in trajs])
        size = self.config.batch_size
        order = self.rng.permutation(len(policy))
        metrics = []
        for start in range(0, max(len(policy) - size + 1, 1), size):
            data = self.data[self.rng.integers(len(self.data), size=size)]
            metrics.append(self.learner.update(DiscriminatorBatch(data, policy[order[start : start + size]])))
        return {**self.report(metrics), **self.last_rewards}
