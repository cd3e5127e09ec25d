"""The shared trainer: what every method needs, around the method's own iteration step.

The `Trainer` builds the method's components and its rollout workers through a
`Runtime` (this process, deterministic for a seed, or Ray actors), then runs the
iteration budget: the method's `step` (sample → replay → update → publish
weights), metrics, the progress bar, evaluation and checkpoint cadence,
recovery of a component that Ray restarted, and resume. Methods
(`orchestrator.algos`) call back into it for the machinery they share, through
what `orchestrator.algos.base.TrainerAPI` lists: `publish` (weights into the
object store once per version), `collect` (workers refreshed when their weights
are too stale, then one coarse collect call each), `check_alive`,
`took_collections` and `worker_restarts`. At the end the trained policy is
exported as the run's MLflow model (`orchestrator.tracking.model`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from orchestrator import checkpoint
from orchestrator.algos.base import Method, method_class
from orchestrator.components.rollout import RolloutActor
from orchestrator.runtime.base import Resources, Runtime, driver_gpus, learner_gpus, worker_gpus
from orchestrator.runtime.cores import assign
from orchestrator.schema import Config
from orchestrator.tracking.base import RunLogger
from orchestrator.tracking.model import deployable, log_policy
from orchestrator.tracking.system import SystemMetrics
from orchestrator.upstream import Upstream
from workers.body.character import Character
from workers.learners.base import Weights

log = logging.getLogger(__name__)


class Trainer:
    def __init__(
        self,
        cfg: Config,
        runtime: Runtime,
        logger: RunLogger,
        character: Character,
        upstream: dict[str, Upstream] | None = None,
    ):
        self.cfg = cfg
        self.runtime = runtime
        self.logger = logger
        self.character = character
        self.state = checkpoint.LoopState()
        self.ckpt_dir = Path(cfg.run_dir) / "checkpoints"
        self.method: Method = method_class(cfg)(cfg, character, upstream)
        r = cfg.runtime
        num_workers = r.rollout_workers if self.method.uses_workers else 0
        components = self.method.components()
        learners = sum(c.role != "replay" for c in components)
        per_worker = worker_gpus(r, cfg.sim, num_workers, learners)
        worker_res = Resources(cpus=r.worker_cpus, gpus=per_worker, max_restarts=r.max_restarts)
        gpu_workers = num_workers if per_worker > 0 and r.worker_gpus == 0 else 0
        learner_res = Resources(
            cpus=r.learner_cpus, gpus=learner_gpus(r, learners, gpu_workers), max_restarts=r.max_restarts
        )
        replay_res = Resources(cpus=0.5, max_restarts=r.max_restarts)
        workers = [f"rollout-{i}" for i in range(num_workers)]
        own = [c.actor for c in components if c.own_core]
        cores = assign(r, own, [c.actor for c in components if not c.own_core] + workers)
        res = [
            replace(replay_res if c.role == "replay" else learner_res, cores=cores.get(c.actor, ())) for c in components
        ]
        worker_res = [replace(worker_res, cores=cores.get(w, ())) for w in workers]
        # Last, a bundle nothing is spawned in: the driver's own evaluation on the workers' GPU, in Ray's accounting.
        driver = driver_gpus(r, cfg.sim, num_workers, learners)
        runtime.reserve(res + worker_res + ([Resources(cpus=0.0, gpus=driver)] if driver else []))
        if r.learner_compile != "eager":
            log.info(
                "runtime.learner_compile=%s: each learner compiles its loss at its first update, minutes the first "
                "time on this machine and seconds after (runtime.learner_compile=eager skips it)",
                r.learner_compile,
            )
        # Components whose states are saved beside each checkpoint, not in it (`checkpoint.replay_path`).
        self.replay_keys = [c.key for c in components if c.role == "replay"]
        self.handles: dict[str, Any] = {
            c.key: runtime.spawn(c.cls, *c.args, name=c.actor, resources=rc, **c.kwargs)
            for c, rc in zip(components, res, strict=True)
        }
        self.workers = [
            runtime.spawn(RolloutActor, cfg, i, type(self.method), name=w, resources=wr)
            for i, (w, wr) in enumerate(zip(workers, worker_res, strict=True))
        ]
        self.worker_versions = [-1] * len(self.workers)
        # Settings the method gives every worker (`configure_workers`), and which of them each worker has.
        self.worker_settings: dict[str, Any] = {}
        self.settings_version = 0
        self.worker_settings_versions = [0] * len(self.workers)
        self.weights_version = -1
        self.weights_ref: Any = None
        self.nonfinite_weights_skipped = 0  # weights refused by `publish` for holding NaN or inf
        self.restarts = 0
        # The stateful components' current lives; one that comes back from a crash is reloaded
        # from the last checkpoint (`check_alive`).
        self.incarnations: dict[str, str | None] = dict.fromkeys(self.handles)
        self.recoveries = 0
        # Checkpoints that may have a copy in the store, oldest first (those of a resumed run's earlier commands too).
        self.in_store: list[Path] = sorted(checkpoint.newest_first(self.ckpt_dir))
        self.forgotten: set[Path] = set()  # deleted from the store by this command
        self.system: SystemMetrics | None = None  # started by `run`
        self.model_uri: str | None = None  # the exported policy's MLflow model, after `run`

    # Shared machinery for the methods ----------------------------------------------
    def publish(self, weights: Weights) -> None:
        """The policy's weights into the object store, once per version; the workers pick them up in `collect`.

        Weights holding a NaN or inf are never published: the workers keep the last good ones, and the
        refusal is counted (`loop/nonfinite_weights_skipped`) and warned about once."""

        def finite(x: Any) -> bool:  # tensors and arrays anywhere in the (possibly nested) state
            if isinstance(x, torch.Tensor):
                return not x.is_floating_point() or bool(torch.isfinite(x).all())
            if isinstance(x, np.ndarray):
                return x.dtype.kind != "f" or bool(np.isfinite(x).all())
            if isinstance(x, dict):
                return all(finite(v) for v in x.values())
            if isinstance(x, list | tuple):
                return all(finite(v) for v in x)
            return not isinstance(x, float) or bool(np.isfinite(x))

        if weights.version != self.weights_version:
            if not finite(weights.state):
                if self.weights_ref is None:
                    raise RuntimeError(f"the first weights to publish (version {weights.version}) are not finite")
                self.nonfinite_weights_skipped += 1
                if self.nonfinite_weights_skipped == 1:
                    log.warning(
                        "weights version %d hold NaN or inf: not published; the workers keep version %d "
                        "(counted in loop/nonfinite_weights_skipped)",
                        weights.version,
                        self.weights_version,
                    )
                return
            if weights.version < self.weights_version:  # the learner was rolled back: every worker refreshes
                self.worker_versions = [-1] * len(self.workers)
            self.weights_ref = self.runtime.put(weights)
            self.weights_version = weights.version

    def configure_workers(self, **settings: Any) -> None:
        """Settings for every rollout worker (`RolloutActor.configure`), sent before its next collect,
        and again to a worker that restarted."""
        self.worker_settings.update(settings)
        self.settings_version += 1

    def collect(self, steps: int, staleness: int) -> list[Any]:
        """One collect call per worker (futures of trajectories); a worker more than `staleness`
        versions behind, or without weights, gets the newest first, and the settings it lacks."""
        pending = []
        for i, worker in enumerate(self.workers):
            if self.worker_settings_versions[i] < self.settings_version:
                self.runtime.call(worker, "configure", self.worker_settings)
                self.worker_settings_versions[i] = self.settings_version
            if self.weights_version - self.worker_versions[i] > staleness or self.worker_versions[i] < 0:
                self.runtime.call(worker, "set_weights", self.weights_ref)
                self.worker_versions[i] = self.weights_version
            pending.append(self.runtime.call(worker, "collect", steps))
        return pending

    def worker_came_back(self, w: int, version: int) -> None:
        """A worker reported weights older than it was sent: it restarted; resend the newest."""
        if version < self.worker_versions[w]:
            self.worker_versions[w] = -1
            self.worker_settings_versions[w] = 0
            self.restarts = -1  # recount now

    def took_collections(self, key: str, infos: list[dict[str, Any]]) -> None:
        """Component `key` took one collection from each worker, in order, each summarised with its
        `incarnation` (popped) and the weights' `version` it was collected with: a component or worker
        that restarted is recovered, and the restart count refreshed."""
        for w, info in enumerate(infos):
            self.check_alive(key, info.pop("incarnation"))
            self.worker_came_back(w, info["version"])
        self.worker_restarts()

    def worker_restarts(self) -> int:
        if self.restarts < 0 or self.state.iteration % 10 == 0:  # the runtime's count costs ~15 ms a worker on Ray
            self.restarts = sum(self.runtime.restarts(w) for w in self.workers)
        return self.restarts

    def check_alive(self, key: str, incarnation: str) -> None:
        """Reload a component that came back from a crash (a new incarnation) from the last checkpoint."""
        known = self.incarnations[key]
        self.incarnations[key] = incarnation
        if known is None or known == incarnation:
            return
        self.recoveries += 1
        path = checkpoint.latest(self.ckpt_dir)
        if path is None:
            log.warning("%s restarted before the first checkpoint: it starts over", key)
            return
        states = self._replay_states(path) if key in self.replay_keys else checkpoint.load(path)
        if key not in states:
            log.warning("%s restarted: no state of it beside %s (algo.loop.replay_keep=0): empty", key, path.name)
            return
        self.runtime.get(self.runtime.call(self.handles[key], "load_state_dict", states[key]))
        log.warning("%s restarted: reloaded from %s", key, path.name)

    # One iteration -----------------------------------------------------------------
    def step(self) -> dict[str, float]:
        t0 = time.perf_counter()
        collected, metrics = self.method.step(self)
        self.state.samples += collected
        self.state.iteration += 1
        elapsed = time.perf_counter() - t0
        metrics["throughput/samples_per_s"] = collected / elapsed
        metrics["throughput/iteration_s"] = elapsed
        metrics["rollout/policy_version"] = float(self.weights_version)
        metrics["rollout/worker_restarts"] = float(self.restarts)
        metrics["loop/recoveries"] = float(self.recoveries)
        metrics["loop/nonfinite_weights_skipped"] = float(self.nonfinite_weights_skipped)
        if self.system is not None:
            metrics.update(self.system.take())
        return metrics

    # Checkpoints -------------------------------------------------------------------
    def save(self) -> Path:
        """`ckpt-N.pt` (networks, optimizers, counters, the workers' states) and, beside it, `replay-N.pt` (the
        replay buffers, written first: a crash between the two leaves no checkpoint without them). The run directory
        keeps `algo.loop.checkpoint_keep` checkpoints, the replay of the newest `replay_keep`; the store the newest
        `tracking.store_checkpoints` checkpoints, never a replay (a stage's consumers read its networks; a resume
        reads the run directory)."""
        rt, loop = self.runtime, self.cfg.algo.loop
        state = {key: rt.get(rt.call(h, "state_dict")) for key, h in self.handles.items()}
        replay = {key: state.pop(key) for key in self.replay_keys}
        state.update(
            loop=asdict(self.state),
            method=self.method.state_dict(),
            workers=rt.get([rt.call(w, "state_dict") for w in self.workers]),
            run_id=self.logger.run_id,
        )
        if replay and loop.replay_keep > 0:
            checkpoint.save(self.ckpt_dir, self.state.iteration, replay, stem=checkpoint.REPLAY_STEM)
        path = checkpoint.save(self.ckpt_dir, self.state.iteration, state)
        self.logger.log_artifact(str(path), "checkpoints")
        self.logger.log_artifact(str(checkpoint.digest_path(path)), "checkpoints")
        self.in_store = [p for p in self.in_store if p != path] + [path]
        while len(self.in_store) > self.cfg.tracking.store_checkpoints:  # deleted in order after the uploads
            self._forget(self.in_store.pop(0))
        checkpoint.prune(self.ckpt_dir, loop.checkpoint_keep, self._forget, loop.replay_keep)
        return path

    def _forget(self, path: Path) -> None:
        """Delete checkpoint `path`'s copy in the store, once (a no-op there when it is gone already)."""
        if path in self.forgotten:  # deleted there when it left the store's newest, now leaving the run directory
            return
        self.forgotten.add(path)
        if path in self.in_store:
            self.in_store.remove(path)
        self.logger.delete_artifact(f"checkpoints/{path.name}")
        self.logger.delete_artifact(f"checkpoints/{checkpoint.digest_path(path).name}")

    def _replay_states(self, path: Path) -> dict[str, Any]:
        """The replay buffers saved with checkpoint `path`: {} when none were (older than the newest kept, or
        `algo.loop.replay_keep=0`); a CheckpointError naming the file when they were and do not load. A checkpoint
        from before they were saved apart holds them itself."""
        state = checkpoint.load(path)
        if all(key in state for key in self.replay_keys):
            return {key: state[key] for key in self.replay_keys}
        replay = checkpoint.replay_path(path)
        return checkpoint.load(replay) if replay.exists() else {}

    def restore(self, path: Path) -> None:
        """Load every component, the method and the workers from `path`; CheckpointError naming the file and
        what does not fit (a resume then tries the checkpoint before it: each load replaces every state)."""
        state = checkpoint.load(path)
        checkpoint.check_layout(path, state, [k for k in self.handles if k not in self.replay_keys])
        try:
            replay = self._replay_states(path) if self.replay_keys else {}
        except checkpoint.CheckpointError as e:  # the networks beside it are good: better than an older checkpoint
            log.warning("resume: replay buffer %s; not used", e)
            replay = {}
        if self.replay_keys and not replay:
            log.warning(
                "resume: %s has no replay buffer beside it (kept for the newest checkpoint only, "
                "algo.loop.replay_keep): it refills from empty, algo.loop.warmup transitions before learning",
                path.name,
            )
        state.update(replay)
        rt = self.runtime
        try:
            loop = checkpoint.LoopState(**state["loop"])
            self.method.load_state_dict(state["method"])
            rt.get([rt.call(h, "load_state_dict", state[key]) for key, h in self.handles.items() if key in state])
            for w, ws in zip(self.workers, state["workers"], strict=True):
                rt.get(rt.call(w, "load_state_dict", ws))
        except Exception as e:
            raise checkpoint.CheckpointError(path, checkpoint.load_error(e)) from None
        self.state = loop

    # The run -----------------------------------------------------------------------
    def run(self) -> dict[str, float]:
        cfg = self.cfg
        self.worker_versions = [-1] * len(self.workers)
        self.method.start(self)
        if cfg.eval.at_start and self.state.iteration == 0 and not self.state.baseline:
            self.state.baseline = self.method.evaluate(self, final=False)
            self.logger.log_metrics(self.state.baseline, step=0)
        self.system = None
        if cfg.tracking.enabled and cfg.tracking.system_metrics_s > 0:
            self.system = SystemMetrics(cfg.tracking.system_metrics_s)
        try:
            last = self._iterate()
        finally:
            if self.system is not None:
                self.system.close()
        self.method.finish(self)
        final = self.method.evaluate(self, final=True)
        self.logger.log_metrics(final, step=self.state.samples)
        self.save()
        self.export_model()
        return {**last, **final}

    def _iterate(self) -> dict[str, float]:
        cfg, loop = self.cfg, self.cfg.algo.loop
        last: dict[str, float] = {}
        deadline = time.monotonic() + loop.max_minutes * 60 if loop.max_minutes > 0 else float("inf")
        # Closed however the loop ends, so that an interrupt's message starts on a line of its own.
        with tqdm(
            total=loop.iterations, initial=self.state.iteration, disable=not cfg.progress, desc=cfg.algo.name
        ) as bar:
            while self.state.iteration < loop.iterations:
                if time.monotonic() >= deadline:
                    log.warning(
                        "algo.loop.max_minutes=%g reached at iteration %d", loop.max_minutes, self.state.iteration
                    )
                    break
                metrics = self.step()
                i = self.state.iteration
                if loop.eval_every and i % loop.eval_every == 0 and i < loop.iterations:
                    metrics.update(self.method.evaluate(self, final=False))
                self.logger.log_metrics(metrics, step=self.state.samples)
                if loop.checkpoint_every and i % loop.checkpoint_every == 0 and i < loop.iterations:
                    self.save()
                bar.update(1)
                bar.set_postfix(samples=self.state.samples, **self.method.progress(metrics))
                last = metrics
        return last

    def export_model(self) -> None:
        """The trained policy as the run's MLflow model (orchestrator/tracking/model.py), when tracked."""
        if not self.cfg.tracking.enabled or not self.cfg.tracking.log_model:
            return
        weights = self.method.policy_weights(self)
        if weights is None:
            return
        method, character, library = type(self.method), *self.method.character_and_library()
        policy = method.make_policy(self.cfg, character)
        found = deployable(policy, weights, character, library, method.sim_config(self.cfg), self.cfg.seed)
        if found is not None:
            self.model_uri = log_policy(self.logger, *found, Path(self.cfg.run_dir))
