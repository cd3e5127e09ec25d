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
frame (Eq. 18–19, `workers.replay.balancing`) and the workers draw their starts, and the
starts of clip switches (`switch_rate`), ∝ 1/max(0.01, V).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from orchestrator.algos.base import Component, ReplayFed, UpdateSchedule
from orchestrator.components.controlvae import VAEActor, WorldModelActor
from orchestrator.components.replay import ReplayActor
from orchestrator.evaluation.protocols import evaluate_controller
from orchestrator.schema import ConfigError, MethodConfig, ReplayLoop
from workers.learners.vae import ControlVAEObjective, state_weight_vector
from workers.learners.world_model import WorldModelConfig
from workers.policies import VAEPolicy
from workers.recorders import TrackingReward
from workers.replay.balancing import FrameValues


@dataclass
class ControlVAELoop(ReplayLoop):
    """ControlVAE's loop: a replay ratio per learner, where synthetic rollouts start, data balancing and the
    trajectory sampler (§3.4)."""

    # Learner samples per collected sample, per learner, over `replay_ratio` (the paper's schedule: world_model 16,
    # vae 48).
    replay_ratios: dict[str, float] = field(default_factory=dict)
    # Where the VAE's synthetic rollouts start. "states": any stored state, drawn singly (the paper's "start states
    # randomly selected from the simulation buffer"), with as many more states for the normaliser as windows would
    # feed it; "windows": the first state of a stored window of rollout_steps transitions (never one of the last
    # rollout_steps - 1 before an end).
    vae_starts: str = "states"
    # Data balancing (§3.4.3): every balance_every iterations (the paper: 200; 0: off), each library frame's value
    # moves toward V* of Eq. 18 (discount balance_gamma) by balance_rate (Eq. 19's rate, not given in the paper),
    # and starts are drawn ∝ 1/max(0.01, V).
    balance_every: int = 200
    balance_rate: float = 0.5
    balance_gamma: float = 0.95
    # The trajectory sampler (§3.4.4): per environment, switches of the reference clip per second of collection
    # (the paper gives no rate; 0: none), and the seconds after a switch in which a fall is counted against it
    # (otherwise a recovery).
    switch_rate: float = 0.0
    switch_window: float = 2.0

    def __post_init__(self) -> None:
        super().__post_init__()
        for key, ratio in self.replay_ratios.items():
            if ratio <= 0:
                raise ConfigError(f"algo.loop.replay_ratios.{key} must be positive, got {ratio}")
        if self.vae_starts not in ("states", "windows"):
            raise ConfigError(f"algo.loop.vae_starts must be 'states' or 'windows', got {self.vae_starts!r}")
        if self.balance_every < 0 or not 0 < self.balance_rate <= 1 or not 0 < self.balance_gamma <= 1:
            raise ConfigError("algo.loop.balance_every must be non-negative, balance_rate and balance_gamma in (0, 1]")
        if self.switch_rate < 0 or self.switch_window <= 0:
            raise ConfigError("algo.loop.switch_rate must be non-negative and algo.loop.switch_window positive")


@dataclass
class ControlVAEAlgo(MethodConfig):
    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    vae: ControlVAEObjective = field(default_factory=ControlVAEObjective)
    loop: ControlVAELoop = field(default_factory=ControlVAELoop)


class ControlVAE(ReplayFed):
    config_class = ControlVAEAlgo
    replay_buffers = 1
    expert = "vae"  # a demos stage can take its posterior as the expert

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        loop = cfg.algo.loop
        # Each learner's updates by its own replay ratio (the credit between iterations is checkpointed).
        ratios = {key: loop.replay_ratios.get(key, loop.replay_ratio) for key in ("world_model", "vae")}
        self.schedules = {key: UpdateSchedule.of(cfg, key, ratio) for key, ratio in ratios.items()}
        self.values: FrameValues | None = None  # data balancing's value per library frame, once it starts
        self.balance = (loop.balance_rate, loop.balance_gamma)

    def components(self) -> list[Component]:
        cfg, b, a = self.cfg, self.character.num_bodies, self.character.num_actions
        return [
            Component("replay", ReplayActor, (cfg, b, a), role="replay"),
            Component("world_model", WorldModelActor, (cfg, b, a), actor="learner-world_model"),
            # 8 updates an iteration to the world model's 4, each slower: the loop waits on this one
            Component("vae", VAEActor, (cfg, b, a), actor="learner-vae", own_core=True),
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
    def publish(self, trainer) -> None:
        """World model → VAE learner; VAE → object store once per version."""
        rt, h = trainer.runtime, trainer.handles
        rt.call(h["vae"], "set_world_model_weights", rt.call(h["world_model"], "get_weights"))
        trainer.publish(rt.get(rt.call(h["vae"], "get_weights")))

    def start(self, trainer) -> None:
        if self.values is not None:  # resumed: the workers draw their starts by the restored values
            trainer.configure_workers(start_weights=self.values.weights())
        super().start(trainer)

    def step(self, trainer) -> tuple[int, dict[str, float]]:
        cfg, rt, h, schedules = self.cfg, trainer.runtime, trainer.handles, self.schedules
        loop = cfg.algo.loop
        t0 = time.perf_counter()
        infos, collected = self.exchange(trainer, "replay")
        t_sample = time.perf_counter() - t0
        replay_size = infos[-1]["size"]
        staleness = [trainer.weights_version - i["version"] for i in infos]

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
                trainer.check_alive(prefix, m.pop("incarnation"))
                metrics.update({f"{prefix}/{k}": v for k, v in m.items()})
            if loop.balance_every and (trainer.state.iteration + 1) % loop.balance_every == 0:
                metrics.update(self.rebalance(trainer))
        t_update = time.perf_counter() - t1

        t2 = time.perf_counter()
        self.publish(trainer)
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

    def rebalance(self, trainer) -> dict[str, float]:
        """Data balancing: the frames' values from the stored trajectories (Eq. 18–19), new start weights
        for the workers; the value and start share of each clip as metrics."""
        _, library = self.character_and_library()
        if self.values is None:
            self.values = FrameValues(library.total_frames, *self.balance)
        rt = trainer.runtime
        count, total = rt.get(
            rt.call(trainer.handles["replay"], "frame_returns", self.values.values, self.values.gamma)
        )
        seen = self.values.update(count, total)
        trainer.configure_workers(start_weights=self.values.weights())
        summary = self.values.clip_summary(library)
        metrics = {"balance/frames_seen": float(len(seen)) / library.total_frames}
        for k, name in enumerate(library.names):
            metrics[f"balance/value/{name}"] = float(summary["value"][k])
            metrics[f"balance/start_share/{name}"] = float(summary["share"][k])
        return metrics

    def evaluate(self, trainer, final: bool) -> dict[str, float]:
        rt = trainer.runtime
        weights = rt.get(rt.call(trainer.handles["vae"], "get_weights"))
        return evaluate_controller(
            self.cfg, *self.character_and_library(), weights, trainer.logger, trainer.state.iteration, final
        )

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
            self.values = FrameValues(self.character_and_library()[1].total_frames, *self.balance)
            self.values.load_state_dict(state["values"])
