"""PPO's learner actor (`learner-ppo`), shared by the PPO methods: AMP, the tracking expert, the task's PPO trainer.

It takes the rollout workers' trajectories as they are (on Ray, as object references resolved
inside the actor, so the data goes from the workers to the learners without passing through the
driver) and returns only metrics.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from orchestrator.components.base import LearnerActor, compiled, learner_device
from orchestrator.schema import Config
from orchestrator.world import seed_of
from workers.learners.ppo import PPOLearner, ppo_rollout
from workers.models.actor_critic import HelperLayout
from workers.types import Trajectory


class PPOActor(LearnerActor):
    """PPO on the workers' trajectories; rewards from the trajectories' `reward` or given (AMP)."""

    def __init__(self, cfg: Config, obs_dim: int, act_dim: int, helper: HelperLayout | None = None):
        super().__init__(cfg)
        ppo = replace(cfg.algo.ppo, seed=seed_of(cfg, 5))
        self.learner = compiled(PPOLearner(obs_dim, act_dim, ppo, learner_device(cfg), helper), cfg)
        self.running_return: np.ndarray | None = None  # per environment, across calls
        self.running_length: np.ndarray | None = None

    def train(self, *trajs: Trajectory, rewards: list[np.ndarray] | None = None) -> dict[str, Any]:
        rollout = ppo_rollout(trajs, rewards)
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
