"""ControlVAE (Yao et al. 2022): a world model and a VAE controller learned together from simulated rollouts.

Components: the replay buffer of simulated transitions (`replay`), the world-model
learner (`learner-world_model`) and the VAE learner (`learner-vae`), which learns
through a frozen copy of the world model. Rollout workers track random clips with
the VAE controller (z from the posterior, or from the prior with probability
`algo.loop.prior_probability`).

One iteration is pipelined: the trajectories of the collect calls issued last
iteration go from the workers to the replay buffer directly, the next collect
calls are issued at once (on Ray they run while the learners update), then both
learners take the updates that the replay ratio makes due, and the VAE's new
weights are published. Locally the same calls run in order.
"""

from __future__ import annotations

import time
from typing import Any

from orchestrator.algos import Component, Method
from orchestrator.components import ReplayActor, VAEActor, WorldModelActor, load_world
from orchestrator.evaluate import evaluate_controller
from workers.policies import VAEPolicy


class ControlVAE(Method):
    sections = ("world_model", "vae")

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.pending: list[Any] = []
        self.world = None
        # Replay-ratio credit carried between iterations, and update counts (checkpointed).
        self.counters = {"world_model_credit": 0.0, "vae_credit": 0.0, "world_model_updates": 0, "vae_updates": 0}

    def components(self) -> list[Component]:
        cfg, b, a = self.cfg, self.character.num_bodies, self.character.num_actions
        return [
            Component("replay", ReplayActor, (cfg, b, a), role="replay"),
            Component("world_model", WorldModelActor, (cfg, b, a), actor="learner-world_model"),
            Component("vae", VAEActor, (cfg, b, a), actor="learner-vae"),
        ]

    @classmethod
    def make_policy(cls, cfg, character) -> VAEPolicy:
        return VAEPolicy(character.num_bodies, character.num_actions, cfg.algo.vae, cfg.algo.loop.prior_probability)

    # The iteration -----------------------------------------------------------------
    def publish(self, t) -> None:
        """World model → VAE learner; VAE → object store once per version."""
        rt, h = t.rt, t.handles
        rt.call(h["vae"], "set_world_model_weights", rt.call(h["world_model"], "get_weights"))
        t.publish(rt.get(rt.call(h["vae"], "get_weights")))

    def start(self, t) -> None:
        self.publish(t)
        self.pending = t.collect(self.cfg.algo.loop.collect_steps, self.cfg.algo.loop.staleness)

    def updates_due(self, collected: int, size: int, length: int, key: str) -> int:
        credit = self.counters[key] + self.cfg.algo.loop.replay_ratio * collected / (size * length)
        n = int(credit)
        self.counters[key] = credit - n
        return n

    def step(self, t) -> tuple[int, dict[str, float]]:
        cfg, rt, h, c = self.cfg, t.rt, t.handles, self.counters
        t0 = time.perf_counter()
        # Trajectories go from the workers to the replay actor directly; only their summaries come back.
        infos = rt.get([rt.call(h["replay"], "add_trajectory", f) for f in self.pending])
        t_sample = time.perf_counter() - t0
        for info in infos:
            t.check_alive("replay", info.pop("incarnation"))
        collected = sum(i["transitions"] for i in infos)
        replay_size = infos[-1]["size"]
        staleness = [t.weights_version - i["version"] for i in infos]
        for w, info in enumerate(infos):
            t.worker_came_back(w, info["version"])
        t.worker_restarts()
        self.pending = t.collect(cfg.algo.loop.collect_steps, cfg.algo.loop.staleness)

        t1 = time.perf_counter()
        metrics: dict[str, float] = {}
        if replay_size >= cfg.algo.loop.warmup:
            wm, vae = cfg.algo.world_model, cfg.algo.vae
            n_wm = self.updates_due(collected, wm.batch_size, wm.rollout_steps, "world_model_credit")
            n_vae = self.updates_due(collected, vae.batch_size, vae.rollout_steps, "vae_credit")
            wm_batches = rt.call(h["replay"], "sample_batches", n_wm, wm.batch_size, wm.rollout_steps)
            vae_batches = rt.call(h["replay"], "sample_batches", n_vae, vae.batch_size, vae.rollout_steps)
            wm_metrics = rt.call(h["world_model"], "train", wm_batches)
            vae_metrics = rt.call(h["vae"], "train", vae_batches)
            for prefix, m in (("world_model", rt.get(wm_metrics)), ("vae", rt.get(vae_metrics))):
                t.check_alive(prefix, m.pop("incarnation"))
                metrics.update({f"{prefix}/{k}": v for k, v in m.items()})
            c["world_model_updates"] += n_wm
            c["vae_updates"] += n_vae
        t_update = time.perf_counter() - t1

        t2 = time.perf_counter()
        self.publish(t)
        t_publish = time.perf_counter() - t2
        stats = rt.get(rt.call(h["replay"], "stats"))
        metrics.update({f"replay/{k}": float(v) for k, v in stats.items()})
        ends = sum(i["episode_ends"] for i in infos)
        metrics.update(
            {
                "throughput/sample_wait_s": t_sample,
                "throughput/update_s": t_update,
                "throughput/publish_s": t_publish,
                "rollout/max_staleness": float(max(staleness)),
                "loop/world_model_updates": float(c["world_model_updates"]),
                "loop/vae_updates": float(c["vae_updates"]),
                "rollout/episode_ends": float(ends),
                "rollout/mean_episode_steps": collected / max(ends, 1),
            }
        )
        return collected, metrics

    def finish(self, t) -> None:
        t.rt.get(self.pending)  # let the last collection finish before saving

    def evaluate(self, t, final: bool) -> dict[str, float]:
        if self.world is None:  # the driver's own character and library, loaded once
            self.world = load_world(self.cfg)
        weights = t.rt.get(t.rt.call(t.handles["vae"], "get_weights"))
        return evaluate_controller(self.cfg, *self.world, weights, t.tracker, t.state.iteration, final)

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"vae": f"{metrics.get('vae/rec', float('nan')):.3g}"}

    def state_dict(self) -> dict[str, Any]:
        return dict(self.counters)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.counters = {k: type(v)(state[k]) for k, v in self.counters.items()}
