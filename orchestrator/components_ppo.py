"""The on-policy learner actors: PPO (`learner-ppo`) and AMP's discriminator (`learner-discriminator`).

Both take the rollout workers' trajectories as they are (on Ray, as object
references resolved inside the actor, so the data goes from the workers to the
learners without passing through the driver) and return only metrics, or, for
the discriminator's `rewards`, one small [T, M] array per worker.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch

from orchestrator.components import LearnerActor, load_world, seed_of
from orchestrator.schema import Config
from workers.learners.discriminator import DiscriminatorBatch, DiscriminatorLearner
from workers.learners.ppo import PPOLearner, Rollout
from workers.motion.library import MotionLibrary
from workers.sim.character import Character
from workers.sim.features import amp_dim, amp_features
from workers.types import Trajectory


def rollout_of(trajs: tuple[Trajectory, ...], rewards: list[np.ndarray] | None) -> Rollout:
    """The workers' trajectories side by side (environments concatenated) as one PPO rollout [T, ΣM]."""

    def cat(key: str) -> np.ndarray:
        return np.concatenate([tr.extras[key] for tr in trajs], axis=1)

    obs = cat("obs")
    final = np.zeros_like(obs)
    offset = 0
    for tr in trajs:
        rows = tr.extras["final_rows"]
        final[rows[:, 0], offset + rows[:, 1]] = tr.extras["final_obs"]
        offset += tr.done.shape[1]
    reward = np.concatenate(rewards, axis=1) if rewards is not None else cat("reward")
    return Rollout(
        obs=obs,
        actions=cat("action"),  # the policy's samples (PD targets, or offsets for a residual policy)
        log_probs=cat("log_prob"),
        rewards=reward,
        dones=np.concatenate([tr.done for tr in trajs], axis=1).astype(np.float32),
        last_obs=np.concatenate([tr.extras["last_obs"] for tr in trajs], axis=0),
        values=None,  # V(o) of the whole rollout in one batch, by the learner before it updates
        truncated=cat("truncated").astype(np.float32),
        final_obs=final,
    )


class PPOActor(LearnerActor):
    """PPO on the workers' trajectories; rewards from the trajectories' `reward` or given (AMP)."""

    def __init__(self, cfg: Config, obs_dim: int, act_dim: int):
        super().__init__()
        torch.set_num_threads(cfg.runtime.torch_threads)
        self.learner = PPOLearner(obs_dim, act_dim, replace(cfg.algo.ppo, seed=seed_of(cfg, 5)))
        self.running_return: np.ndarray | None = None  # per environment, across calls
        self.running_length: np.ndarray | None = None

    def train(self, *trajs: Trajectory, rewards: list[np.ndarray] | None = None) -> dict[str, Any]:
        rollout = rollout_of(trajs, rewards)
        lag = self.learner.version - min(tr.version for tr in trajs)  # 0 when collection is synchronous
        metrics = self.learner.train_on_rollout(rollout)
        metrics.update(self._episodes(np.asarray(rollout.rewards), np.asarray(rollout.dones) > 0))
        out = self.report([metrics])
        out["trajectory_versions"] = [int(tr.version) for tr in trajs]
        out["policy_lag"] = float(lag)
        return out

    def _episodes(self, rewards: np.ndarray, dones: np.ndarray) -> dict[str, float]:
        """Undiscounted return and length of the episodes that ended in this rollout."""
        if self.running_return is None or self.running_return.shape != rewards.shape[1:]:
            self.running_return = np.zeros(rewards.shape[1])
            self.running_length = np.zeros(rewards.shape[1])
        returns, lengths = [], []
        for t in range(rewards.shape[0]):
            self.running_return += rewards[t]
            self.running_length += 1
            ended = np.flatnonzero(dones[t])
            returns.extend(self.running_return[ended].tolist())
            lengths.extend(self.running_length[ended].tolist())
            self.running_return[ended] = 0.0
            self.running_length[ended] = 0.0
        out = {"episodes": float(len(returns))}
        if returns:
            out.update(episode_return=float(np.mean(returns)), episode_length=float(np.mean(lengths)))
        return out


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
        super().__init__()
        torch.set_num_threads(cfg.runtime.torch_threads)
        character, library = load_world(cfg)
        self.config = cfg.algo.discriminator
        self.weights = cfg.algo.amp
        self.data = reference_transitions(character, library)
        self.learner = DiscriminatorLearner(amp_dim(character), self.config, seed=seed_of(cfg, 6))
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
