"""What the PPO methods share (AMP, the tracking expert, the task policy trained by PPO): the on-policy iteration.

Components: the PPO learner (`learner-ppo`) and whatever the method adds (AMP's
discriminator). Rollout workers run the actor-critic (`GaussianPolicy`) on the
method's observation.

One iteration: every worker collects `algo.loop.collect_steps` control steps of
its environments with the newest weights (PPO is on-policy: by default collection
is synchronous, every worker is refreshed to the newest version first; with
`algo.loop.overlap` the next batch is collected while the learners train on this
one, one iteration behind); the
trajectories go to the learners directly (object references on Ray); the method
turns them into rewards and starts any other learner's update on them
(`rewards_and_updates`: AMP's discriminator scores them, then learns from them;
by default the rewards the workers recorded); PPO takes one iteration on them; the
new weights are published once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from orchestrator.algos.base import Component, Method
from orchestrator.components.ppo import PPOActor
from orchestrator.evaluation.protocols import evaluate_imitation
from orchestrator.schema import MethodConfig, PPOLoop
from workers.body.features import StateLayout
from workers.learners.ppo import PPOConfig, build_actor_critic
from workers.policies import GaussianPolicy, observation_dim

METRIC_PREFIX = {"discriminator": "disc"}  # DESIGN's metric namespaces where they differ from the key


@dataclass
class PPOAlgo(MethodConfig):
    """What the config of a method trained by this loop has: PPO's section and the PPO loop."""

    ppo: PPOConfig = field(default_factory=PPOConfig)
    loop: PPOLoop = field(default_factory=PPOLoop)


class OnPolicy(Method):
    """A PPO method; subclasses set `observation` (or `observation_of` where a config decides it) and may add
    components and rewards; their configs extend `PPOAlgo`."""

    config_class = PPOAlgo
    observation = "state"
    residual = False  # actions are offsets from the reference's next pose (workers.policies.GaussianPolicy)
    expert = "ppo"  # a demos or PULSE stage can distil its actor

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.pending: list[Any] = []  # the batch being collected, with `algo.loop.overlap`

    @classmethod
    def observation_of(cls, cfg) -> str:
        """What the policy observes under `cfg` (`workers.policies.OBSERVATIONS`)."""
        return cls.observation

    def components(self) -> list[Component]:
        obs_dim = observation_dim(self.observation_of(self.cfg), StateLayout(self.character.num_bodies).dim)
        return [Component("ppo", PPOActor, (self.cfg, obs_dim, self.character.num_actions), actor="learner-ppo")]

    @classmethod
    def make_policy(cls, cfg, character) -> GaussianPolicy:
        obs = cls.observation_of(cfg)
        module = build_actor_critic(
            observation_dim(obs, StateLayout(character.num_bodies).dim), character.num_actions, cfg.algo.ppo
        )
        return GaussianPolicy(module, obs, cls.residual)

    def rewards_and_updates(self, trainer, trajectories: list[Any]) -> tuple[Any, dict[str, Any]]:
        """The rewards PPO trains on, and the updates of the method's other learners on the same trajectories:
        (a future of the rewards [T, M] per trajectory, or None for the `reward` the workers recorded;
        futures of the other learners' metrics, by component key)."""
        return None, {}

    def publish(self, trainer) -> None:
        rt = trainer.runtime
        trainer.publish(rt.get(rt.call(trainer.handles["ppo"], "get_weights")))

    def start(self, trainer) -> None:
        self.publish(trainer)
        if self.cfg.algo.loop.overlap:
            self.pending = trainer.collect(self.cfg.algo.loop.collect_steps, staleness=0)

    def step(self, trainer) -> tuple[int, dict[str, float]]:
        cfg, rt = self.cfg, trainer.runtime
        t0 = time.perf_counter()
        steps = cfg.algo.loop.collect_steps
        if cfg.algo.loop.overlap:  # this batch was collected last iteration; the next starts now
            trajectories, self.pending = self.pending, trainer.collect(steps, staleness=0)
        else:
            trajectories = trainer.collect(steps, staleness=0)
        rewards, others = self.rewards_and_updates(trainer, trajectories)
        ppo = rt.call(trainer.handles["ppo"], "train", *trajectories, rewards=rewards)
        metrics: dict[str, float] = {}
        for key, future in {"ppo": ppo, **others}.items():
            m = rt.get(future)
            trainer.check_alive(key, m.pop("incarnation"))
            prefix = METRIC_PREFIX.get(key, key)
            for w, v in enumerate(m.pop("trajectory_versions", [])):
                trainer.worker_came_back(w, v)
            metrics.update({f"{prefix}/{k}": float(v) for k, v in m.items()})
        trainer.worker_restarts()
        t_update = time.perf_counter() - t0
        t1 = time.perf_counter()
        self.publish(trainer)
        collected = cfg.algo.loop.collect_steps * cfg.runtime.envs_per_worker * len(trainer.workers)
        metrics.update({"throughput/collect_and_update_s": t_update, "throughput/publish_s": time.perf_counter() - t1})
        return collected, metrics

    def finish(self, trainer) -> None:
        trainer.runtime.get(self.pending)  # let an overlapping collection finish before the final checkpoint

    def evaluate(self, trainer, final: bool) -> dict[str, float]:
        character, library = self.character_and_library()
        rt = trainer.runtime
        weights = rt.get(rt.call(trainer.handles["ppo"], "get_weights"))
        policy = self.make_policy(self.cfg, character)
        policy.set_weights(weights)
        return evaluate_imitation(self.cfg, character, library, policy, trainer.logger, trainer.state.iteration, final)

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"return": f"{metrics.get('ppo/episode_return', float('nan')):.3g}"}
