"""ControlVAE (Yao et al. 2022): a world model and a VAE controller learned together from simulated rollouts.

Components: the replay buffer of simulated transitions (`replay`), the world-model
learner (`learner-world_model`) and the VAE learner (`learner-vae`), which learns
through a frozen copy of the world model. Rollout workers track random clips with
the VAE controller (z from the posterior, or from the prior with probability
`algo.loop.prior_probability`).

One iteration is pipelined: the trajectories of the collect calls issued last
iteration go from the workers to the replay buffer directly, the next collect
calls are issued at once (on Ray they run while the learners update), then each
learner takes the updates that its replay ratio makes due (`algo.loop.replay_ratios`),
and the VAE's new weights are published. Locally the same calls run in order.

The collection is the paper's (§3.4.3–3.4.4): the workers record each state's
reward of Eq. 20 (its mean is the learning curve, `rollout/reward`); every
`balance_every` iterations the replay's trajectories update a value per library
frame (Eq. 18–19, `workers.balancing`) and the workers draw their starts, and the
starts of clip switches (`switch_rate`), ∝ 1/max(0.01, V).
"""

from __future__ import annotations

import time
from typing import Any

from orchestrator.algos import Component, Method, UpdateSchedule
from orchestrator.components import ReplayActor, VAEActor, WorldModelActor, load_world
from orchestrator.evaluate import evaluate_controller
from workers.balancing import FrameValues
from workers.learners.vae import state_weight_vector
from workers.policies import VAEPolicy
from workers.recorders import TrackingReward


class ControlVAE(Method):
    sections = ("world_model", "vae")

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.pending: list[Any] = []
        self.world = None
        loop = cfg.algo.loop
        # Each learner's updates by its own replay ratio (the credit between iterations is checkpointed).
        self.schedules = {key: UpdateSchedule.of(cfg, key) for key in ("world_model", "vae")}
        self.values: FrameValues | None = None  # data balancing's value per library frame, once it starts
        self.balance = (loop.balance_rate, loop.balance_gamma)

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

    @classmethod
    def make_recorders(cls, cfg, character) -> list[TrackingReward]:
        """Each collected state's reward of Eq. 20, with the reconstruction loss's weights W."""
        return [TrackingReward(state_weight_vector(character.num_bodies, cfg.algo.vae.state_weights).numpy())]

    @classmethod
    def worker_options(cls, cfg) -> dict[str, float]:
        return {"switch_rate": cfg.algo.loop.switch_rate, "switch_window": cfg.algo.loop.switch_window}

    # The iteration -----------------------------------------------------------------
    def publish(self, t) -> None:
        """World model → VAE learner; VAE → object store once per version."""
        rt, h = t.rt, t.handles
        rt.call(h["vae"], "set_world_model_weights", rt.call(h["world_model"], "get_weights"))
        t.publish(rt.get(rt.call(h["vae"], "get_weights")))

    def start(self, t) -> None:
        if self.values is not None:  # resumed: the workers draw their starts by the restored values
            t.configure_workers(start_weights=self.values.weights())
        self.publish(t)
        self.pending = t.collect(self.cfg.algo.loop.collect_steps, self.cfg.algo.loop.staleness)

    def step(self, t) -> tuple[int, dict[str, float]]:
        cfg, rt, h, schedules = self.cfg, t.rt, t.handles, self.schedules
        loop = cfg.algo.loop
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
        self.pending = t.collect(loop.collect_steps, loop.staleness)

        t1 = time.perf_counter()
        metrics: dict[str, float] = {}
        if replay_size >= loop.warmup:
            wm, vae = cfg.algo.world_model, cfg.algo.vae
            n_wm, n_vae = schedules["world_model"].due(collected), schedules["vae"].due(collected)
            wm_batches = rt.call(h["replay"], "sample_batches", n_wm, wm.batch_size, wm.rollout_steps)
            sample = "sample_start_batches" if loop.vae_starts == "states" else "sample_batches"
            vae_batches = rt.call(h["replay"], sample, n_vae, vae.batch_size, vae.rollout_steps)
            wm_metrics = rt.call(h["world_model"], "train", wm_batches)
            vae_metrics = rt.call(h["vae"], "train", vae_batches)
            for prefix, m in (("world_model", rt.get(wm_metrics)), ("vae", rt.get(vae_metrics))):
                t.check_alive(prefix, m.pop("incarnation"))
                metrics.update({f"{prefix}/{k}": v for k, v in m.items()})
            if loop.balance_every and (t.state.iteration + 1) % loop.balance_every == 0:
                metrics.update(self.rebalance(t))
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
                "loop/world_model_updates": float(schedules["world_model"].updates),
                "loop/vae_updates": float(schedules["vae"].updates),
                "rollout/episode_ends": float(ends),
                "rollout/mean_episode_steps": collected / max(ends, 1),
                # ControlVAE's learning curve: the mean of exp(-L_rec / 20) over the collected states (Eq. 20).
                "rollout/reward": sum(i["reward_sum"] for i in infos) / max(collected, 1),
            }
        )
        for key in ("switches", "switch_falls", "switch_recoveries"):
            if key in infos[0]:
                metrics[f"rollout/{key}"] = float(sum(i[key] for i in infos))
        return collected, metrics

    def rebalance(self, t) -> dict[str, float]:
        """Data balancing: the frames' values from the stored trajectories (Eq. 18–19), new start weights
        for the workers; the value and start share of each clip as metrics."""
        if self.world is None:
            self.world = load_world(self.cfg)
        library = self.world[1]
        if self.values is None:
            self.values = FrameValues(library.total_frames, *self.balance)
        count, total = t.rt.get(t.rt.call(t.handles["replay"], "frame_returns", self.values.values, self.values.gamma))
        seen = self.values.update(count, total)
        t.configure_workers(start_weights=self.values.weights())
        summary = self.values.clip_summary(library)
        metrics = {"balance/frames_seen": float(len(seen)) / library.total_frames}
        for k, name in enumerate(library.names):
            metrics[f"balance/value/{name}"] = float(summary["value"][k])
            metrics[f"balance/start_share/{name}"] = float(summary["share"][k])
        return metrics

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
        state: dict[str, Any] = {"values": None if self.values is None else self.values.state_dict()}
        for key, schedule in self.schedules.items():
            state.update(schedule.state_dict(key))
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for key, schedule in self.schedules.items():
            schedule.load_state_dict(state, key)
        if state.get("values") is not None:
            if self.world is None:
                self.world = load_world(self.cfg)
            self.values = FrameValues(self.world[1].total_frames, *self.balance)
            self.values.load_state_dict(state["values"])
