"""What the PPO methods share (AMP, the tracking expert, later the task policy): the on-policy iteration.

Components: the PPO learner (`learner-ppo`) and whatever the method adds (AMP's
discriminator). Rollout workers run the actor-critic (`GaussianPolicy`) on the
method's observation.

One iteration: every worker collects `algo.loop.collect_steps` control steps of
its environments with the newest weights (PPO is on-policy: by default collection
is synchronous, every worker is refreshed to the newest version first; with
`algo.loop.overlap` the next batch is collected while the learners train on this
one, one iteration behind); the
trajectories go to the learners directly (object references on Ray); the method
turns them into rewards (`rewards`, None for rewards recorded by the workers);
PPO takes one iteration on them; the new weights are published once.
"""

from __future__ import annotations

import time
from typing import Any

from orchestrator.algos import Component, Method
from orchestrator.components import load_world
from orchestrator.components_ppo import PPOActor
from orchestrator.evaluate import evaluate_imitation
from workers.learners.ppo import build_actor_critic
from workers.policies import GaussianPolicy, observation_dim
from workers.sim.features import StateLayout

METRIC_PREFIX = {"discriminator": "disc"}  # DESIGN's metric namespaces where they differ from the key


class OnPolicy(Method):
    """A PPO method; subclasses set `observation` and may add components and rewards."""

    observation = "state"
    residual = False  # actions are offsets from the reference's next pose (workers.policies.GaussianPolicy)

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.world = None
        self.pending: list[Any] = []  # the batch being collected, with `algo.loop.overlap`

    def components(self) -> list[Component]:
        obs_dim = observation_dim(self.observation, StateLayout(self.character.num_bodies).dim)
        return [Component("ppo", PPOActor, (self.cfg, obs_dim, self.character.num_actions), actor="learner-ppo")]

    @classmethod
    def make_policy(cls, cfg, character) -> GaussianPolicy:
        obs_dim = observation_dim(cls.observation, StateLayout(character.num_bodies).dim)
        module = build_actor_critic(obs_dim, character.num_actions, cfg.algo.ppo)
        return GaussianPolicy(module, cls.observation, cls.residual)

    def rewards(self, t, trajectories: list[Any]) -> tuple[Any, dict[str, Any]]:
        """(A future of the rewards [T, M] per trajectory, or None to use the recorded `reward`;
        futures of other learners' metrics, by component key)."""
        return None, {}

    def publish(self, t) -> None:
        t.publish(t.rt.get(t.rt.call(t.handles["ppo"], "get_weights")))

    def start(self, t) -> None:
        self.publish(t)
        if self.cfg.algo.loop.overlap:
            self.pending = t.collect(self.cfg.algo.loop.collect_steps, staleness=0)

    def step(self, t) -> tuple[int, dict[str, float]]:
        cfg, rt = self.cfg, t.rt
        t0 = time.perf_counter()
        steps = cfg.algo.loop.collect_steps
        if cfg.algo.loop.overlap:  # this batch was collected last iteration; the next starts now
            trajectories, self.pending = self.pending, t.collect(steps, staleness=0)
        else:
            trajectories = t.collect(steps, staleness=0)
        rewards, others = self.rewards(t, trajectories)
        ppo = rt.call(t.handles["ppo"], "train", *trajectories, rewards=rewards)
        metrics: dict[str, float] = {}
        for key, future in {"ppo": ppo, **others}.items():
            m = rt.get(future)
            t.check_alive(key, m.pop("incarnation"))
            prefix = METRIC_PREFIX.get(key, key)
            for w, v in enumerate(m.pop("trajectory_versions", [])):
                t.worker_came_back(w, v)
            metrics.update({f"{prefix}/{k}": float(v) for k, v in m.items()})
        t.worker_restarts()
        t_update = time.perf_counter() - t0
        t1 = time.perf_counter()
        self.publish(t)
        collected = cfg.algo.loop.collect_steps * cfg.runtime.envs_per_worker * len(t.workers)
        metrics.update({"throughput/collect_and_update_s": t_update, "throughput/publish_s": time.perf_counter() - t1})
        return collected, metrics

    def finish(self, t) -> None:
        t.rt.get(self.pending)  # let an overlapping collection finish before the final checkpoint

    def evaluate(self, t, final: bool) -> dict[str, float]:
        if self.world is None:  # the driver's own character and library, loaded once
            self.world = load_world(self.cfg)
        weights = t.rt.get(t.rt.call(t.handles["ppo"], "get_weights"))
        policy = self.make_policy(self.cfg, self.world[0])
        policy.set_weights(weights)
        return evaluate_imitation(self.cfg, *self.world, policy, t.tracker, t.state.iteration, final)

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"return": f"{metrics.get('ppo/episode_return', float('nan')):.3g}"}
