"""Expert data (`algo=demos`): noisy rollouts of an expert over every clip, as a dataset artifact.

PhysicsVAE (Sec. 5.1.1) trains on state-action pairs of its imitation experts: ten
rollouts per clip with Gaussian action noise ε = 0.05. The expert is the upstream
stage `algo.needs.expert`: a `tracker` run by default (its PPO actor's mean action,
offset from the reference), or a `controlvae` run (its posterior, z = μ_q). With
`algo.demos.experts=per_clip` (the default, as the paper learns one imitation controller per
clip) that stage is trained once per clip of `motion.clips`, on that clip alone (roles
`expert.0`, `expert.1`, ...), and a mirrored clip is driven by its clip's expert mirrored
(`workers.policies.ExpertPolicy`); `shared` uses one expert for every clip. The rollout
workers run the episodes (`RolloutWorker.demonstrate`), each from a clip's frame 0, for
`algo.demos.seconds` on a looping clip or to the last frame of a one-shot clip, ending
early on a fall.

Outputs (artifacts under `demos/`): `demos.npz` (`workers.demos.DemoSet`: states,
actions, clip, frame, episode ends) and `manifest.json`: the expert runs, the clips,
counts, and the experts' own quality on these rollouts, per clip and over all (time until
fall, the share that stayed up to the end, tracking error), which bounds everything trained
on them and is reported by every run that uses them (`expert/...` metrics).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator import world
from orchestrator.algos.base import Component, Method
from orchestrator.schema import ConfigError, MethodConfig
from orchestrator.upstream import DEMOS_FILE, MANIFEST_FILE, RUN_ID, Upstream, expert_weights
from workers.body.mirror import mirror_maps
from workers.demos import DemoSet
from workers.learners.base import Weights
from workers.policies import ExpertPolicy


@dataclass
class DemosConfig:
    # Expert rollouts per clip of the motion config, from its frame 0 (PhysicsVAE Sec. 5.1.1: 10).
    rollouts_per_clip: int = 10
    # Gaussian noise added to the expert's (mean) action, std in radians of PD target (PhysicsVAE: 0.05).
    noise: float = 0.05
    # Length of a rollout: a looping clip is tracked this long, a one-shot clip to its last frame; a
    # rollout also ends where the expert falls.
    seconds: float = 10.0
    # Whose rollouts: "per_clip", one imitation controller per clip as PhysicsVAE trains them (§5.1.1): each
    # clip of motion.clips gets its own `algo.needs.expert` stage, trained on that clip alone (mirror off), and
    # a mirrored clip is driven by its clip's expert mirrored (workers/body/mirror.py); "shared", the one
    # expert stage trained on every clip (ControlVAE-style multi-clip tracking).
    experts: str = "per_clip"

    def __post_init__(self) -> None:
        if self.experts not in ("per_clip", "shared"):
            raise ConfigError(f"algo.demos.experts: expected 'per_clip' or 'shared', got {self.experts!r}")
        if self.rollouts_per_clip < 1:
            raise ConfigError(f"algo.demos.rollouts_per_clip must be at least 1, got {self.rollouts_per_clip}")
        if self.noise < 0:
            raise ConfigError(f"algo.demos.noise must be non-negative, got {self.noise}")
        if self.seconds <= 0:
            raise ConfigError(f"algo.demos.seconds must be positive, got {self.seconds}")


@dataclass
class DemosAlgo(MethodConfig):
    demos: DemosConfig = field(default_factory=DemosConfig)


class Demos(Method):
    config_class = DemosAlgo
    needs = ("expert",)

    @classmethod
    def needs_of(cls, cfg) -> dict[str, str]:
        """With per-clip experts, the expert stage once per clip (`expert.<i>`), each trained on its clip alone."""
        needs = dict(cfg.algo.needs)
        if cfg.algo.demos.experts == "shared":
            return needs
        spec = needs.pop("expert")
        if RUN_ID.fullmatch(spec.strip()):
            raise ConfigError(
                f"algo.needs.expert={spec}: one run cannot be every clip's expert under algo.demos.experts=per_clip "
                "(name a stage, or set algo.demos.experts=shared)"
            )
        for i, clip in enumerate(cfg.motion.clips):
            if any(c.isspace() or c in ",[]" for c in str(clip)):
                raise ConfigError(
                    f"motion.clips[{i}]: {clip!r} cannot name a per-clip expert stage (space, comma or [])"
                )
            needs[f"expert.{i}"] = f"{spec} motion.clips=[{clip}] motion.mirror=false"
        return needs

    def components(self) -> list[Component]:
        return []

    def experts(self) -> list[Upstream]:
        """The expert stages, one per clip of motion.clips (per_clip) or one."""
        if self.cfg.algo.demos.experts == "shared":
            return [self.upstream["expert"]]
        return [self.upstream[f"expert.{i}"] for i in range(len(self.cfg.motion.clips))]

    def clip_experts(self) -> tuple[np.ndarray, np.ndarray]:
        """(the expert of each library clip, whether it runs mirrored): the library holds each clip of
        motion.clips followed, with motion.mirror, by its mirror."""
        n, per = len(self.cfg.motion.clips), 2 if self.cfg.motion.mirror else 1
        if self.cfg.algo.demos.experts == "shared":
            return np.zeros(n * per, int), np.zeros(n * per, bool)
        return np.repeat(np.arange(n), per), np.tile([False, True][:per], n)

    def expert_weights(self) -> Weights:
        experts = [expert_weights(up) for up in self.experts()]
        if self.cfg.algo.demos.experts == "shared":
            return experts[0]
        which, mirrored = self.clip_experts()
        payload = {
            "kind": "per_clip",
            "experts": [e.state for e in experts],
            "clip_expert": which.tolist(),
            "clip_mirrored": mirrored.tolist(),
        }
        if mirrored.any():
            payload["mirror"] = mirror_maps(self.character)
        return Weights(max(e.version for e in experts), payload)

    @classmethod
    def make_policy(cls, cfg, character) -> ExpertPolicy:
        return ExpertPolicy(character.num_bodies, character.num_actions, cfg.algo.demos.noise)

    @classmethod
    def sim_config(cls, cfg):
        """Falls detected (they end a rollout); no tracking-failure end and no cap (the rollout's length is set)."""
        return replace(world.sim_config(cfg), threads=cfg.runtime.sim_threads)

    def start(self, trainer) -> None:
        trainer.publish(self.expert_weights())

    def rollout_steps(self) -> np.ndarray:
        """[clips] control steps of a rollout of each library clip: `seconds` on a looping clip, to its end else."""
        _, library = self.character_and_library()
        wanted = max(1, int(round(self.cfg.algo.demos.seconds * self.cfg.character.control_hz)))
        return np.where(library.loop, wanted, np.minimum(wanted, library.num_frames - 1))

    def jobs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(clip, rollout index, control steps) of every rollout, clip by clip."""
        _, library = self.character_and_library()
        d = self.cfg.algo.demos
        clips = np.repeat(np.arange(library.num_clips), d.rollouts_per_clip)
        rollouts = np.tile(np.arange(d.rollouts_per_clip), library.num_clips)
        return clips, rollouts, self.rollout_steps()[clips]

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
        for name, clip in manifest["per_clip"].items():  # each clip's rollouts: stayed up, and tracking error
            for key in ("stayed_up_fraction", "tracking_error", "seconds_mean"):
                metrics[f"expert/clip/{name}/{key}"] = float(clip[key])
        metrics["throughput/demos_s"] = time.perf_counter() - t0
        return demos.num_transitions, metrics

    def manifest(self, demos: DemoSet) -> dict[str, Any]:
        _, library = self.character_and_library()
        hz = self.cfg.character.control_hz
        seconds = demos.episode_length / hz
        # A rollout stayed up when it ran its full length (10 s on a looping clip, a one-shot clip to its end).
        full = ~demos.episode_fell & (demos.episode_length >= self.rollout_steps()[demos.episode_clip])
        experts = self.experts()
        which, mirrored = self.clip_experts()
        per_clip = {}
        for c, name in enumerate(library.names):
            e = demos.episode_clip == c
            up = experts[which[c]]
            per_clip[name] = {
                "expert_run": up.run_id,
                "mirrored": bool(mirrored[c]),
                "episodes": int(e.sum()),
                "transitions": int(demos.episode_length[e].sum()),
                "fell": int(demos.episode_fell[e].sum()),
                "stayed_up_fraction": float(full[e].mean()),
                "seconds_mean": float(seconds[e].mean()),
                "tracking_error": float(demos.episode_tracking_error[e].mean()),
            }
        own = {}
        for up in experts:
            own.update({k.removeprefix("eval/"): v for k, v in up.metrics().items() if k.startswith("eval/")})
        fell = demos.episode_fell
        return {
            "expert_run": experts[0].run_id if len(experts) == 1 else None,
            "expert_runs": [up.run_id for up in experts],
            "experts": self.cfg.algo.demos.experts,
            "expert_algo": experts[0].name,
            "expert_stage_hash": experts[0].stage_hash if len(experts) == 1 else None,
            "clips": list(library.names),
            "rollouts_per_clip": self.cfg.algo.demos.rollouts_per_clip,
            "noise": self.cfg.algo.demos.noise,
            "seconds": self.cfg.algo.demos.seconds,
            "counts": {"episodes": demos.num_episodes, "transitions": demos.num_transitions},
            # The experts with the noise, on these rollouts: seconds until they fell (rollouts that did not
            # fall count their full length), the share that fell, the share that stayed up to the end, and the
            # tracking error; with one expert, its own evaluation too (own/...).
            "expert": {
                "time_until_fall_mean": float(seconds.mean()),
                "fell_fraction": float(fell.mean()),
                "stayed_up_fraction": float(full.mean()),
                "tracking_error_mean": float(demos.episode_tracking_error.mean()),
                **({f"own/{k}": float(v) for k, v in own.items() if "/" not in k} if len(experts) == 1 else {}),
            },
            "per_clip": per_clip,
        }

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"fell": f"{metrics.get('expert/fell_fraction', float('nan')):.2f}"}
