"""The rollout worker as a component: `workers.rollout.RolloutWorker` running the policy of the config's method."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from orchestrator.components.base import actor_preamble
from orchestrator.schema import Config
from orchestrator.world import load_character_and_library, seed_of
from workers.body.character import Character
from workers.learners.base import Weights
from workers.policies import Policy
from workers.recorders import Recorder
from workers.rollout import RolloutWorker
from workers.sim.env import SimConfig
from workers.types import Trajectory


class MethodLike(Protocol):
    """What a rollout worker asks of a method's class (`orchestrator.algos.base.Method` has it)."""

    def make_policy(self, cfg: Config, character: Character) -> Policy: ...
    def make_recorders(self, cfg: Config, character: Character) -> list[Recorder]: ...
    def sim_config(self, cfg: Config) -> SimConfig: ...
    def worker_options(self, cfg: Config) -> dict[str, Any]: ...


class RolloutActor:
    """A rollout worker running the policy of the config's method (`Method.make_policy`), with what that
    method records (`make_recorders`), on its collection simulator (`sim_config`). `method` is the method's
    class, handed over by the trainer (a class pickles by reference)."""

    def __init__(self, cfg: Config, worker_id: int, method: type[MethodLike]):
        actor_preamble(cfg)
        character, library = load_character_and_library(cfg)
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
