"""The training loop: sample → add to replay → update → publish weights → report, each phase timed.

One `Trainer` drives the components through a `Runtime`; the same code runs them
in this process (deterministic for a seed) or as Ray actors. Collection is
pipelined: the workers' next collect calls are issued before the learners
update, so on Ray they run while the learners work; locally they run in order.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from orchestrator import checkpoint
from orchestrator.components import ReplayActor, RolloutActor, VAEActor, WorldModelActor, load_world
from orchestrator.evaluate import evaluate
from orchestrator.runtime.base import Resources, Runtime
from orchestrator.schema import Config
from orchestrator.tracking.base import Tracker

log = logging.getLogger(__name__)


@dataclass
class LoopState:
    """Counters that a checkpoint restores."""

    iteration: int = 0
    samples: int = 0  # environment transitions collected (the metrics' step)
    world_model_credit: float = 0.0  # replay-ratio credit carried between iterations
    vae_credit: float = 0.0
    world_model_updates: int = 0
    vae_updates: int = 0


class Trainer:
    def __init__(self, cfg: Config, runtime: Runtime, tracker: Tracker, num_bodies: int, action_dim: int):
        self.cfg = cfg
        self.rt = runtime
        self.tracker = tracker
        self.state = LoopState()
        self.ckpt_dir = Path(cfg.run_dir) / "checkpoints"
        r = cfg.runtime
        worker_res = Resources(cpus=r.worker_cpus, max_restarts=r.max_restarts)
        learner_res = Resources(cpus=r.learner_cpus, gpus=r.learner_gpus, max_restarts=r.max_restarts)
        replay_res = Resources(cpus=0.5, max_restarts=r.max_restarts)
        runtime.reserve([replay_res, learner_res, learner_res] + [worker_res] * r.rollout_workers)
        self.replay = runtime.spawn(ReplayActor, cfg, num_bodies, action_dim, name="replay", resources=replay_res)
        self.world_model = runtime.spawn(
            WorldModelActor, cfg, num_bodies, action_dim, name="learner-world_model", resources=learner_res
        )
        self.vae = runtime.spawn(VAEActor, cfg, num_bodies, action_dim, name="learner-vae", resources=learner_res)
        self.workers = [
            runtime.spawn(RolloutActor, cfg, i, name=f"rollout-{i}", resources=worker_res)
            for i in range(r.rollout_workers)
        ]
        self.worker_versions = [-1] * len(self.workers)
        self.weights_version = -1
        self.weights_ref: Any = None
        self.pending: list[Any] = []
        self.restarts = 0
        # The stateful components' current lives; one that comes back from a crash is reloaded
        # from the last checkpoint (`check_alive`).
        self.incarnations: dict[str, str | None] = {"replay": None, "world_model": None, "vae": None}
        self.recoveries = 0
        self.world = None

    # Phases ------------------------------------------------------------------
    def publish(self) -> None:
        """World model → VAE learner; VAE → object store once per version."""
        wm = self.rt.call(self.world_model, "get_weights")
        self.rt.call(self.vae, "set_world_model_weights", wm)
        weights = self.rt.get(self.rt.call(self.vae, "get_weights"))
        if weights.version != self.weights_version:
            if weights.version < self.weights_version:  # the learner was rolled back: every worker refreshes
                self.worker_versions = [-1] * len(self.workers)
            self.weights_ref = self.rt.put(weights)
            self.weights_version = weights.version

    def check_alive(self, name: str, incarnation: str) -> None:
        """Reload a component that came back from a crash (a new incarnation) from the last checkpoint."""
        known = self.incarnations[name]
        self.incarnations[name] = incarnation
        if known is None or known == incarnation:
            return
        self.recoveries += 1
        path = checkpoint.latest(self.ckpt_dir)
        if path is None:
            log.warning("%s restarted before the first checkpoint: it starts over", name)
            return
        handle = {"replay": self.replay, "world_model": self.world_model, "vae": self.vae}[name]
        self.rt.get(self.rt.call(handle, "load_state_dict", checkpoint.load(path)[name]))
        log.warning("%s restarted: reloaded from %s", name, path.name)

    def launch_collection(self) -> None:
        loop = self.cfg.algo.loop
        self.pending = []
        for i, worker in enumerate(self.workers):
            if self.weights_version - self.worker_versions[i] > loop.staleness or self.worker_versions[i] < 0:
                self.rt.call(worker, "set_weights", self.weights_ref)
                self.worker_versions[i] = self.weights_version
            self.pending.append(self.rt.call(worker, "collect", loop.collect_steps))

    def updates_due(self, collected: int, size: int, length: int, credit: float) -> tuple[int, float]:
        credit += self.cfg.algo.loop.replay_ratio * collected / (size * length)
        n = int(credit)
        return n, credit - n

    def step(self) -> dict[str, float]:
        cfg, rt, s = self.cfg, self.rt, self.state
        t0 = time.perf_counter()
        # Trajectories go from the workers to the replay actor directly; only their summaries come back.
        infos = rt.get([rt.call(self.replay, "add_trajectory", f) for f in self.pending])
        t_sample = time.perf_counter() - t0
        for info in infos:
            self.check_alive("replay", info.pop("incarnation"))
        collected = sum(i["transitions"] for i in infos)
        s.samples += collected
        replay_size = infos[-1]["size"]
        staleness = [self.weights_version - i["version"] for i in infos]
        for w, info in enumerate(infos):
            if info["version"] < self.worker_versions[w]:
                # The worker came back from a crash with its initial weights: resend the newest.
                self.worker_versions[w] = -1
                self.restarts = -1  # recount now
        if self.restarts < 0 or s.iteration % 10 == 0:  # the runtime's count costs ~15 ms a worker on Ray
            self.restarts = sum(self.rt.restarts(w) for w in self.workers)
        self.launch_collection()

        t1 = time.perf_counter()
        metrics: dict[str, float] = {}
        if replay_size >= cfg.algo.loop.warmup:
            wm, vae = cfg.algo.world_model, cfg.algo.vae
            n_wm, s.world_model_credit = self.updates_due(
                collected, wm.batch_size, wm.rollout_steps, s.world_model_credit
            )
            n_vae, s.vae_credit = self.updates_due(collected, vae.batch_size, vae.rollout_steps, s.vae_credit)
            wm_batches = rt.call(self.replay, "sample_batches", n_wm, wm.batch_size, wm.rollout_steps)
            vae_batches = rt.call(self.replay, "sample_batches", n_vae, vae.batch_size, vae.rollout_steps)
            wm_metrics = rt.call(self.world_model, "train", wm_batches)
            vae_metrics = rt.call(self.vae, "train", vae_batches)
            for prefix, m in (("world_model", rt.get(wm_metrics)), ("vae", rt.get(vae_metrics))):
                self.check_alive(prefix, m.pop("incarnation"))
                metrics.update({f"{prefix}/{k}": v for k, v in m.items()})
            s.world_model_updates += n_wm
            s.vae_updates += n_vae
        t_update = time.perf_counter() - t1

        t2 = time.perf_counter()
        self.publish()
        t_publish = time.perf_counter() - t2
        s.iteration += 1
        elapsed = time.perf_counter() - t0
        stats = rt.get(rt.call(self.replay, "stats"))
        metrics.update({f"replay/{k}": float(v) for k, v in stats.items()})
        metrics.update(
            {
                "throughput/samples_per_s": collected / elapsed,
                "throughput/iteration_s": elapsed,
                "throughput/sample_wait_s": t_sample,
                "throughput/update_s": t_update,
                "throughput/publish_s": t_publish,
                "rollout/max_staleness": float(max(staleness)),
                "rollout/policy_version": float(self.weights_version),
                "loop/world_model_updates": float(s.world_model_updates),
                "loop/vae_updates": float(s.vae_updates),
            }
        )
        ends = sum(i["episode_ends"] for i in infos)
        metrics["rollout/worker_restarts"] = float(self.restarts)
        metrics["loop/recoveries"] = float(self.recoveries)
        metrics["rollout/episode_ends"] = float(ends)
        metrics["rollout/mean_episode_steps"] = collected / max(ends, 1)
        return metrics

    # Checkpoints ---------------------------------------------------------------
    def save(self) -> Path:
        rt = self.rt
        state = {
            "loop": asdict(self.state),
            "world_model": rt.get(rt.call(self.world_model, "state_dict")),
            "vae": rt.get(rt.call(self.vae, "state_dict")),
            "replay": rt.get(rt.call(self.replay, "state_dict")),
            "workers": rt.get([rt.call(w, "state_dict") for w in self.workers]),
            "run_id": self.tracker.run_id,
        }
        path = checkpoint.save(self.ckpt_dir, self.state.iteration, state)
        self.tracker.log_artifact(str(path), "checkpoints")
        return path

    def restore(self, path: Path) -> None:
        state = checkpoint.load(path)
        rt = self.rt
        self.state = LoopState(**state["loop"])
        rt.get(rt.call(self.world_model, "load_state_dict", state["world_model"]))
        rt.get(rt.call(self.vae, "load_state_dict", state["vae"]))
        rt.get(rt.call(self.replay, "load_state_dict", state["replay"]))
        for w, ws in zip(self.workers, state["workers"], strict=True):
            rt.get(rt.call(w, "load_state_dict", ws))

    # The run -------------------------------------------------------------------
    def run(self) -> dict[str, float]:
        cfg, loop = self.cfg, self.cfg.algo.loop
        self.publish()
        self.worker_versions = [-1] * len(self.workers)
        self.launch_collection()
        bar = tqdm(total=loop.iterations, initial=self.state.iteration, disable=not cfg.progress, desc="training")
        last: dict[str, float] = {}
        while self.state.iteration < loop.iterations:
            metrics = self.step()
            i = self.state.iteration
            if loop.eval_every and i % loop.eval_every == 0 and i < loop.iterations:
                metrics.update(self.evaluate(final=False))
            self.tracker.log_metrics(metrics, step=self.state.samples)
            if loop.checkpoint_every and i % loop.checkpoint_every == 0 and i < loop.iterations:
                self.save()
            bar.update(1)
            bar.set_postfix(samples=self.state.samples, vae=f"{metrics.get('vae/rec', float('nan')):.3g}")
            last = metrics
        bar.close()
        self.rt.get(self.pending)  # let the last collection finish before saving
        final = self.evaluate(final=True)
        self.tracker.log_metrics(final, step=self.state.samples)
        self.save()
        return {**last, **final}

    def evaluate(self, final: bool) -> dict[str, float]:
        if self.world is None:  # the driver's own character and library, loaded once
            self.world = load_world(self.cfg)
        weights = self.rt.get(self.rt.call(self.vae, "get_weights"))
        return evaluate(self.cfg, *self.world, weights, self.tracker, self.state.iteration, final)
