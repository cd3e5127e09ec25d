"""The task learner (`learner-task` of `algo=task`) and how a skill stage's frozen networks are read.

`skill_model` reads a skill stage (a run with a VAE controller: controlvae, physicsvae or pulse):
its VAE config and decoder/prior weights, whether a task acts as a residual on its
prior's mean (PULSE's `prior_action`; always for the others), and, for the
model-based trainer, the world model to learn through (ControlVAE's own; PhysicsVAE's
simulation layer, from its world_model stage, when that stage's layer integrates: Table 2's
regress layer predicts features and cannot be rolled out). Anything else is refused with the
stage and run named.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orchestrator.components.base import LearnerActor, compiled, learner_device
from orchestrator.schema import Config
from orchestrator.upstream import StageError, Upstream, existing_run, layer_state
from orchestrator.world import seed_of
from workers.learners.task import GoalBuffer, TaskLearner
from workers.learners.world_model import build_world_model
from workers.task.policy import skill_controller
from workers.types import Trajectory


def skill_model(up: Upstream, world_model: bool) -> dict[str, Any]:
    """{"name", "config": VAEConfig, "module", "prior_action", and with `world_model`: "world_model":
    (WorldModelConfig, state dict)} of the skill stage `up`: a run with a VAE controller (controlvae,
    physicsvae, pulse); a StageError naming it if it is not one."""
    cfg = up.config()
    name = cfg.algo.name
    if getattr(cfg.algo, "vae", None) is None:
        raise StageError(f"{up.describe()}: a {name} run is not a skill model (it has no VAE controller)")
    state = up.checkpoint()
    vae = state.get("vae")
    if not isinstance(vae, dict):
        raise StageError(f"{up.describe()}: its checkpoint has no vae state")
    module = vae["learner"]["module"] if "learner" in vae else vae.get("module")
    if module is None:
        raise StageError(f"{up.describe()}: its checkpoint's vae state has no weights")
    # PULSE's prior-action switch (Table 3); the other skill models' tasks always act on the prior's mean.
    pulse = getattr(cfg.algo, "pulse", None)
    prior_action = bool(pulse.prior_action) if pulse is not None else True
    out = {"name": name, "config": cfg.algo.vae, "module": module, "prior_action": prior_action}
    if world_model:
        out["world_model"] = _world_model(up, cfg, state)
    return out


def _world_model(up: Upstream, cfg: Config, state: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
    """The skill stage's own world model (ControlVAE), else that of its world_model stage (PhysicsVAE's layer)."""
    if "world_model" in state and hasattr(cfg.algo, "world_model"):
        return cfg.algo.world_model, state["world_model"]["module"]
    if "world_model" in up.lineage:
        cache = up.cache.parent / f"{up.role}.world_model"
        layer = existing_run(f"{up.role}.world_model", up.lineage["world_model"], up.uri, cache)
        layer_cfg = layer.config().algo.world_model
        if layer_cfg.kind != "integrate":
            raise StageError(
                f"{up.describe()}: its simulation layer (world_model.kind={layer_cfg.kind}) predicts features and "
                "cannot be rolled out by the model-based task trainer; use algo.task.trainer=ppo, or a world_model "
                "stage with algo.world_model.kind=integrate"
            )
        return layer_cfg, layer_state(layer)
    raise StageError(
        f"{up.describe()}: a {cfg.algo.name} skill model has no world model to learn through; use algo.task.trainer=ppo"
    )


class TaskActor(LearnerActor):
    """The task policy's learner with the frozen skill model and world model, and B_g (`GoalBuffer`)."""

    def __init__(self, cfg: Config, num_bodies: int, action_dim: int, skill: Upstream):
        super().__init__(cfg, seed_offset=5)
        payload = skill_model(skill, world_model=True)  # read here: a restarted actor needs nothing from the driver
        controller = skill_controller(payload, num_bodies, action_dim)
        wm_cfg, wm_state = payload["world_model"]
        wm = build_world_model(num_bodies, action_dim, wm_cfg, 1.0 / cfg.character.control_hz)
        wm.load_state_dict(wm_state)
        task = cfg.algo.task
        self.learner = compiled(
            TaskLearner(controller, wm, action_dim, task, payload["prior_action"], learner_device(cfg)), cfg
        )
        self.buffer = GoalBuffer(task.buffer_size)
        self.rng = np.random.default_rng(seed_of(cfg, 6))
        self.steps = task.rollout_steps

    def add_trajectory(self, traj: Trajectory) -> dict[str, Any]:
        """Keep the states and goals of a collection; what the loop logs of it."""
        self.buffer.add(traj.states, traj.extras["goal"])
        terms = {k.removeprefix("reward/"): float(v.sum()) for k, v in traj.extras.items() if k.startswith("reward/")}
        return {
            "transitions": int(traj.done.size),
            "size": len(self.buffer),
            "episode_ends": int(traj.done.sum()),
            "reward_sum": float(traj.extras["reward"].sum()),
            "deviation_sum": float(np.degrees(traj.extras["helper_deviation"]).sum()),
            "terms": terms,
            "version": int(traj.version),
            "incarnation": self.incarnation,
        }

    def train(self, updates: int) -> dict[str, Any]:
        batch = self.learner.config.batch_size
        return self.report(
            [self.learner.update(self.buffer.sample(batch, self.steps, self.rng)) for _ in range(updates)]
        )

    def state_dict(self) -> dict[str, Any]:
        return {
            "learner": self.learner.state_dict(),
            "buffer": self.buffer.state_dict(),
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state["learner"])
        self.buffer.load_state_dict(state["buffer"])
        self.rng.bit_generator.state = state["rng"]
