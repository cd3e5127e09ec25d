"""Downstream tasks on a frozen skill model (ControlVAE §4, PhysicsVAE §4, PULSE §4).

The upstream `skill` stage (`algo.needs.skill`: a controlvae, physicsvae or pulse
run) gives the frozen decoder and prior, and for the model-based trainer the
frozen world model. The task policy outputs a residual μ_g on the prior's mean
(ControlVAE Eq. 21, PULSE Eq. 4) and, with σ > 0, the helper branch
Δa = σ·tanh(H(s, z)) (PhysicsVAE Eq. 2). Goals (`algo.task.task`) are drawn per
episode and redrawn at `algo.task.change_rate`; they are part of the policy's input.

Trainer `model` (ControlVAE §4.2): rollout workers run the task policy in the
simulator (`workers.task_policy`), their states and goal sequences go to the task
learner (`learner-task`) directly, which keeps the newest `buffer_size` of them
(B_g) and takes the updates its replay ratio makes due: N rollouts of T steps
through the frozen world model, Eq. 22's losses. Trainer `ppo` is
`orchestrator.algos.task_ppo` (PPO in the simulator, reward e^(−L_g)).

Evaluation (`workers.evaluation.tasks`): the normalised return and success rate over a
fixed set of goals, the style score (the applied action's deviation from the
decoder's own, degrees) and the time until fall under the task policy. At the start
the skill stage's own evaluation is copied into this run as `skill/...`, so a
sweep over skill stages can set them beside the task's results.
"""

from __future__ import annotations

import time
from typing import Any

from orchestrator.algos import Component, Method, UpdateSchedule
from orchestrator.components import load_world
from orchestrator.components_task import TaskActor, skill_model
from orchestrator.evaluate_task import evaluate_task
from workers.task_policy import TaskRolloutPolicy


class Task(Method):
    sections = ("task", "ppo")
    needs = ("skill",)

    def __new__(cls, cfg, character, upstream=None):
        if cfg.algo.task.trainer == "ppo":  # the other trainer is its own class (PPO's loop)
            from orchestrator.algos.task_ppo import TaskPPO

            return TaskPPO(cfg, character, upstream)
        return super().__new__(cls)

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.pending: list[Any] = []
        self.world = None
        self.skill: dict[str, Any] | None = None
        self.schedule = UpdateSchedule.of(cfg, "task")

    def skill_payload(self) -> dict[str, Any]:
        """The frozen decoder and prior the workers and the evaluation run (downloaded once)."""
        if self.skill is None:  # with the model-based trainer, a skill model without a world model fails here
            model_based = self.cfg.algo.task.trainer == "model"
            self.skill = skill_model(self.upstream["skill"], world_model=model_based)
        return self.skill

    def components(self) -> list[Component]:
        self.skill_payload()  # a skill stage that is not one fails here, before any actor starts
        b, a = self.character.num_bodies, self.character.num_actions
        return [Component("task", TaskActor, (self.cfg, b, a, self.upstream["skill"]), actor="learner-task")]

    @classmethod
    def make_policy(cls, cfg, character) -> TaskRolloutPolicy:
        if cfg.algo.task.trainer == "ppo":
            from orchestrator.algos.task_ppo import TaskPPO

            return TaskPPO.make_policy(cfg, character)
        return TaskRolloutPolicy(character.num_bodies, character.num_actions, cfg.algo.task, cfg.character.control_hz)

    # The iteration -----------------------------------------------------------------
    def publish(self, t) -> None:
        t.publish(t.rt.get(t.rt.call(t.handles["task"], "get_weights")))

    def start(self, t) -> None:
        skill = self.skill_payload()
        t.configure_workers(skill={k: skill[k] for k in ("config", "module", "prior_action")})
        copy_skill_metrics(t, self.upstream["skill"])
        self.publish(t)
        self.pending = t.collect(self.cfg.algo.loop.collect_steps, self.cfg.algo.loop.staleness)

    def step(self, t) -> tuple[int, dict[str, float]]:
        cfg, rt, h = self.cfg, t.rt, t.handles
        loop = cfg.algo.loop
        t0 = time.perf_counter()
        infos = rt.get([rt.call(h["task"], "add_trajectory", f) for f in self.pending])
        t.took_collections("task", infos)
        collected = sum(i["transitions"] for i in infos)
        self.pending = t.collect(loop.collect_steps, loop.staleness)
        metrics: dict[str, float] = {}
        if infos[-1]["size"] >= loop.warmup:
            m = rt.get(rt.call(h["task"], "train", self.schedule.due(collected)))
            t.check_alive("task", m.pop("incarnation"))
            metrics.update({f"task/{k}": float(v) for k, v in m.items()})
        self.publish(t)
        ends = sum(i["episode_ends"] for i in infos)
        metrics.update(
            {
                "rollout/task_reward": sum(i["reward_sum"] for i in infos) / max(collected, 1),
                "rollout/helper_deviation_deg": sum(i["deviation_sum"] for i in infos) / max(collected, 1),
                "rollout/episode_ends": float(ends),
                "rollout/mean_episode_steps": collected / max(ends, 1),
                "loop/task_updates": float(self.schedule.updates),
                "throughput/step_s": time.perf_counter() - t0,
            }
        )
        for term in infos[0].get("terms", {}):
            metrics[f"rollout/{term}"] = sum(i["terms"][term] for i in infos) / max(collected, 1)
        return collected, metrics

    def finish(self, t) -> None:
        t.rt.get(self.pending)

    def evaluate(self, t, final: bool) -> dict[str, float]:
        weights = t.rt.get(t.rt.call(t.handles["task"], "get_weights"))
        if self.world is None:
            self.world = load_world(self.cfg)
        policy = self.make_policy(self.cfg, self.world[0])
        policy.configure({"skill": self.skill_payload()})
        policy.set_weights(weights)
        return evaluate_task(self.cfg, *self.world, policy, t.tracker, t.state.iteration, final)

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"reward": f"{metrics.get('rollout/task_reward', float('nan')):.3g}"}

    def state_dict(self) -> dict[str, Any]:
        return self.schedule.state_dict("task")

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.schedule.load_state_dict(state, "task")


def copy_skill_metrics(t, up) -> None:
    """The skill stage's own final evaluation, as skill/... metrics of this run (once, at its start)."""
    copied = {f"skill/{k.removeprefix('eval/')}": v for k, v in up.metrics().items() if k.startswith("eval/")}
    if copied and t.state.iteration == 0:
        t.tracker.log_metrics(copied, step=0)
