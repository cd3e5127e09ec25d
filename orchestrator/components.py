"""The components the loop wires together, as plain classes that build their own world.

Each is constructed from the validated config inside whatever process hosts it
(this one, or a Ray actor), loads the character and the motion library there,
and exposes coarse methods: a rollout worker collects hundreds of steps per call,
a learner takes a list of batches per call. None of them knows where it runs.
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from orchestrator.schema import Config
from workers.learners.base import Learner, Weights
from workers.learners.vae import VAEBatch, VAELearner
from workers.learners.world_model import WorldModelBatch, WorldModelLearner
from workers.models import body_state
from workers.models.world_model import WorldModel
from workers.motion.library import MotionLibrary
from workers.replay import ReplayBuffer
from workers.rollout import RolloutWorker
from workers.sim.character import Character
from workers.sim.env import SimConfig
from workers.types import StartBatch, Trajectory, WindowBatch


def load_world(cfg: Config) -> tuple[Character, MotionLibrary]:
    kwargs = {"self_collision": cfg.character.self_collision}
    character = Character.load(cfg.character.xml, **kwargs) if cfg.character.xml else Character.load(**kwargs)
    library = MotionLibrary.load(
        character,
        cfg.motion.clips,
        fps=cfg.character.control_hz,
        mirror=cfg.motion.mirror,
        cache_dir=cfg.motion.cache_dir,
        joint_map=dict(cfg.motion.joint_map) or None,
    )
    return character, library


def sim_config(cfg: Config) -> SimConfig:
    """The simulator as evaluation runs it: the character's rates, falls detected."""
    return SimConfig(sim_hz=cfg.character.sim_hz, control_hz=cfg.character.control_hz, terrain=cfg.terrain)


def collection_sim_config(cfg: Config) -> SimConfig:
    """The simulator as the rollout workers run it: the loop's termination rules."""
    loop = cfg.algo.loop
    return replace(
        sim_config(cfg),
        max_episode_steps=loop.max_episode_steps,
        threads=cfg.runtime.sim_threads,
        end_on_fall=loop.end_on_fall,
    )


def mean_metrics(metrics: list[dict[str, float]]) -> dict[str, float]:
    if not metrics:
        return {}
    keys = metrics[-1].keys()
    out = {k: float(np.mean([m[k] for m in metrics if k in m])) for k in keys}
    out["updates"] = float(len(metrics))
    return out


def seed_of(cfg: Config, offset: int) -> int:
    return cfg.seed * 1000 + offset


def incarnation() -> str:
    """Tells one life of a component from the next: a restarted Ray actor is a new process."""
    return f"{os.getpid()}-{time.time_ns()}"


class RolloutActor:
    """A rollout worker running the policy of the config's method (`Method.make_policy`)."""

    def __init__(self, cfg: Config, worker_id: int):
        from orchestrator.algos import method_class

        torch.set_num_threads(cfg.runtime.torch_threads)
        character, library = load_world(cfg)
        method = method_class(cfg.algo._target_)
        self.worker = RolloutWorker(
            character,
            library,
            cfg.runtime.envs_per_worker,
            method.make_policy(cfg, character),
            method.sim_config(cfg),
            seed=seed_of(cfg, 100 + worker_id),
            worker_id=worker_id,
            recorders=method.make_recorders(cfg, character),
            **method.worker_options(cfg),
        )

    def set_weights(self, weights: Weights) -> int:
        self.worker.set_weights(weights)
        return weights.version

    def configure(self, settings: dict[str, Any]) -> None:
        """Settings the loop changes during training: `start_weights` [library frames] (data balancing);
        the rest go to the policy, if it takes settings (the task policy's frozen skill model)."""
        if "start_weights" in settings:
            self.worker.library.set_frame_weights(settings["start_weights"])
        if hasattr(self.worker.policy, "configure"):
            self.worker.policy.configure(settings)

    def collect(self, steps: int) -> Trajectory:
        return self.worker.collect(steps)

    def demonstrate(self, clip_ids: np.ndarray, max_steps: np.ndarray) -> list[dict[str, Any]]:
        return self.worker.demonstrate(clip_ids, max_steps)

    def stats(self) -> dict[str, float]:
        return self.worker.stats()

    def state_dict(self) -> dict[str, Any]:
        return self.worker.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.worker.load_state_dict(state)


class ReplayActor(ReplayBuffer):
    def __init__(self, cfg: Config, num_bodies: int, action_dim: int):
        super().__init__(cfg.algo.loop.replay_capacity, num_bodies, action_dim, seed=seed_of(cfg, 1))
        self.incarnation = incarnation()
        self.cfg = cfg
        self.library: MotionLibrary | None = None  # loaded when data balancing first asks

    def add_trajectory(self, trajectory: Trajectory) -> dict[str, Any]:
        """Store a trajectory; a summary for the loop (the trajectory itself stays here)."""
        self.add(trajectory)
        extras = trajectory.extras
        counts = ("switches", "switch_falls", "switch_recoveries")
        return {
            "transitions": int(trajectory.actions.shape[0] * trajectory.actions.shape[1]),
            "version": int(trajectory.version),
            "episode_ends": int(trajectory.done.sum()),
            "size": len(self),
            "incarnation": self.incarnation,
            "reward_sum": float(extras["reward"].sum()) if "reward" in extras else 0.0,
            **{k: int(extras[k]) for k in counts if k in extras},
        }

    def frame_returns(self, values: np.ndarray, gamma: float) -> tuple[np.ndarray, np.ndarray]:
        """Data balancing (ControlVAE Eq. 18): (visits, summed V*) per library frame over the stored
        trajectories, bootstrapped with `values` [library frames]."""
        from workers.balancing import frame_sums, library_rows

        if self.library is None:
            _, self.library = load_world(self.cfg)
        lib = self.library
        clip, frame, returns = self.discounted_returns(gamma, lambda c, f: values[library_rows(lib, c, f)])
        return frame_sums(library_rows(lib, clip, frame), returns, lib.total_frames)

    def sample_batches(self, count: int, size: int, length: int) -> list[WindowBatch]:
        """`count` batches of windows; none from an empty buffer, which is one that Ray has just
        restarted (the loop reloads it from the last checkpoint when it reports its new life)."""
        if len(self) == 0:
            return []
        return [self.sample_windows(size, length) for _ in range(count)]

    def sample_start_batches(self, count: int, size: int, length: int) -> list[StartBatch]:
        """`count` batches of `size` single stored states (ControlVAE's VAE starts), each with
        `size · (length + 1)` more for the state normaliser: as many as windows of `length` feed it."""
        if len(self) == 0:
            return []
        return [self.sample_starts(size, size * (length + 1)) for _ in range(count)]


class LearnerActor:
    """What both learner actors share: weights, checkpoints, and the report every `train` returns."""

    learner: Learner

    def __init__(self) -> None:
        self.incarnation = incarnation()

    def report(self, metrics: list[dict[str, float]]) -> dict[str, Any]:
        """Mean metrics of the updates, the weights' version, and this actor's incarnation."""
        out: dict[str, Any] = mean_metrics(metrics)
        out["version"] = float(self.learner.version)
        out["incarnation"] = self.incarnation
        return out

    def get_weights(self) -> Weights:
        return self.learner.get_weights()

    def state_dict(self) -> dict[str, Any]:
        return self.learner.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state)


class WorldModelActor(LearnerActor):
    def __init__(self, cfg: Config, num_bodies: int, action_dim: int):
        super().__init__()
        torch.set_num_threads(cfg.runtime.torch_threads)
        torch.manual_seed(seed_of(cfg, 2))
        self.learner = WorldModelLearner(num_bodies, action_dim, 1.0 / cfg.character.control_hz, cfg.algo.world_model)

    def train(self, batches: list[WindowBatch]) -> dict[str, Any]:
        return self.report([self.learner.update(WorldModelBatch(b.states, b.actions)) for b in batches])


class VAEActor(LearnerActor):
    """The VAE learner with a frozen copy of the world model and the library it draws references from."""

    def __init__(self, cfg: Config, num_bodies: int, action_dim: int):
        super().__init__()
        torch.set_num_threads(cfg.runtime.torch_threads)
        torch.manual_seed(seed_of(cfg, 3))
        _, self.library = load_world(cfg)
        wm = cfg.algo.world_model
        world_model = WorldModel(
            num_bodies, action_dim, wm.hidden, wm.activation, 1.0 / cfg.character.control_hz, wm.integrator
        )
        self.learner = VAELearner(num_bodies, action_dim, cfg.algo.vae, world_model=world_model, seed=seed_of(cfg, 4))
        self.world_model_version = -1

    def set_world_model_weights(self, weights: Weights) -> int:
        self.learner.set_world_model_weights(weights)
        self.world_model_version = weights.version
        return weights.version

    def train(self, batches: list[WindowBatch] | list[StartBatch]) -> dict[str, Any]:
        """One update per batch: each window's first state (or each single state) starts a synthetic
        rollout that tracks the reference clip following its frame."""
        steps = self.learner.config.rollout_steps
        metrics = []
        for b in batches:
            reference = body_state.reference_windows(self.library, b.clip_id, b.frame, steps)
            if isinstance(b, StartBatch):
                batch = VAEBatch(b.states[:, None], reference, norm_states=b.norm_states)
            else:
                batch = VAEBatch(b.states, reference)
            metrics.append(self.learner.update(batch))
        return {**self.report(metrics), "world_model_version": float(self.world_model_version)}

    def state_dict(self) -> dict[str, Any]:
        return {"learner": self.learner.state_dict(), "world_model": self.learner.world_model.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state["learner"])
        self.learner.world_model.load_state_dict(state["world_model"])
