"""Expert data (`algo=demos`): noisy rollouts of an expert over every clip, as a dataset artifact.

PhysicsVAE (Sec. 5.1.1) trains on state-action pairs of its imitation experts: ten
rollouts per clip with Gaussian action noise ε = 0.05. The expert is the upstream
stage `algo.needs.expert`: a `tracker` run by default (its PPO actor's mean action,
offset from the reference), or a `controlvae` run (its posterior, z = μ_q). The rollout
workers run the episodes (`RolloutWorker.demonstrate`), each from a clip's frame 0, for
`algo.demos.seconds` on a looping clip or to the last frame of a one-shot clip, ending
early on a fall.

Outputs (artifacts under `demos/`): `demos.npz` (`workers.demos.DemoSet`: states,
actions, clip, frame, episode ends) and `manifest.json`: the expert run, the clips,
counts, and the expert's own quality on these rollouts (time until fall, tracking
error), which bounds everything trained on them and is reported by every run that uses
them (`expert/...` metrics).
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.algos.base import Component, Method
from orchestrator.upstream import DEMOS_FILE, MANIFEST_FILE, expert_weights
from orchestrator.world import evaluation_sim_config
from workers.demos import DemoSet
from workers.policies import ExpertPolicy


class Demos(Method):
    sections = ("demos",)
    needs = ("expert",)

    def components(self) -> list[Component]:
        return []

    @classmethod
    def make_policy(cls, cfg, character) -> ExpertPolicy:
        return ExpertPolicy(character.num_bodies, character.num_actions, cfg.algo.demos.noise)

    @classmethod
    def sim_config(cls, cfg):
        """Falls detected (they end a rollout); no tracking-failure end and no cap (the rollout's length is set)."""
        return replace(evaluation_sim_config(cfg), threads=cfg.runtime.sim_threads)

    def start(self, trainer) -> None:
        trainer.publish(expert_weights(self.upstream["expert"]))

    def jobs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(clip, rollout index, control steps) of every rollout, clip by clip."""
        _, library = self.character_and_library()
        d = self.cfg.algo.demos
        wanted = max(1, int(round(d.seconds * self.cfg.character.control_hz)))
        steps = np.where(library.loop, wanted, np.minimum(wanted, library.num_frames - 1))
        clips = np.repeat(np.arange(library.num_clips), d.rollouts_per_clip)
        rollouts = np.tile(np.arange(d.rollouts_per_clip), library.num_clips)
        return clips, rollouts, steps[clips]

    def step(self, trainer) -> tuple[int, dict[str, float]]:
        rt = trainer.runtime
        t0 = time.perf_counter()
        clips, rollouts, steps = self.jobs()
        n = len(trainer.workers)
        pending = []
        for w, worker in enumerate(trainer.workers):
            rt.call(worker, "set_weights", trainer.weights_ref)
            pending.append(rt.call(worker, "demonstrate", clips[w::n], steps[w::n]))
        episodes: list[Any] = [None] * len(clips)
        for w, result in enumerate(rt.get(pending)):
            episodes[w::n] = result
        for ep, r in zip(episodes, rollouts, strict=True):
            ep["rollout"] = int(r)
        demos = DemoSet.from_episodes(episodes)
        run_dir = Path(self.cfg.run_dir)
        demos.save(run_dir / DEMOS_FILE)
        manifest = self.manifest(demos)
        (run_dir / MANIFEST_FILE).write_text(json.dumps(manifest, indent=2))
        trainer.logger.log_artifact(str(run_dir / DEMOS_FILE), "demos")
        trainer.logger.log_artifact(str(run_dir / MANIFEST_FILE), "demos")
        metrics = {f"demos/{k}": float(v) for k, v in manifest["counts"].items()}
        metrics.update({f"expert/{k}": float(v) for k, v in manifest["expert"].items()})
        metrics["throughput/demos_s"] = time.perf_counter() - t0
        return demos.num_transitions, metrics

    def manifest(self, demos: DemoSet) -> dict[str, Any]:
        _, library = self.character_and_library()
        hz = self.cfg.character.control_hz
        seconds = demos.episode_length / hz
        up = self.upstream["expert"]
        per_clip = {}
        for c, name in enumerate(library.names):
            e = demos.episode_clip == c
            per_clip[name] = {
                "episodes": int(e.sum()),
                "transitions": int(demos.episode_length[e].sum()),
                "fell": int(demos.episode_fell[e].sum()),
                "seconds_mean": float(seconds[e].mean()),
                "tracking_error": float(demos.episode_tracking_error[e].mean()),
            }
        expert_eval = {k.removeprefix("eval/"): v for k, v in up.metrics().items() if k.startswith("eval/")}
        fell = demos.episode_fell
        return {
            "expert_run": up.run_id,
            "expert_algo": up.name,
            "expert_stage_hash": up.stage_hash,
            "clips": list(library.names),
            "rollouts_per_clip": self.cfg.algo.demos.rollouts_per_clip,
            "noise": self.cfg.algo.demos.noise,
            "seconds": self.cfg.algo.demos.seconds,
            "counts": {"episodes": demos.num_episodes, "transitions": demos.num_transitions},
            # The expert with the noise, on these rollouts: seconds until it fell (rollouts that did not
            # fall count their full length), the share that fell, and its tracking error.
            "expert": {
                "time_until_fall_mean": float(seconds.mean()),
                "fell_fraction": float(fell.mean()),
                "tracking_error_mean": float(demos.episode_tracking_error.mean()),
                **{f"own/{k}": float(v) for k, v in expert_eval.items() if "/" not in k},
            },
            "per_clip": per_clip,
        }

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"fell": f"{metrics.get('expert/fell_fraction', float('nan')):.2f}"}
