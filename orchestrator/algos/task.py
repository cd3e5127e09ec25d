"""Downstream tasks on a frozen skill model (ControlVAE §4, PhysicsVAE §4, PULSE §4).

The upstream `skill` stage (`algo.needs.skill`: a controlvae, physicsvae or pulse
run) gives the frozen decoder and prior, and for the model-based trainer the
frozen world model. The task policy outputs a residual μ_g on the prior's mean
(ControlVAE Eq. 21, PULSE Eq. 4) and, with σ > 0, the helper branch
Δa = σ·tanh(H(s, z)) (PhysicsVAE Eq. 2). Goals (`algo.task.task`) are drawn per
episode and redrawn at `algo.task.change_rate`; they are part of the policy's input.

Trainer `model` (ControlVAE §4.2): rollout workers run the task policy in the
simulator (`workers.task.policy`), their states and goal sequences go to the task
learner (`learner-task`) directly, which keeps the newest `buffer_size` of them
(B_g) and takes the updates its replay ratio makes due: N rollouts of T steps
through the frozen world model, Eq. 22's losses.

Trainer `ppo` (`TaskPPO`, below): the comparison ControlVAE draws against its model-based
learner, and how PhysicsVAE and PULSE train their task policies: PPO (the same learner,
`learner-ppo`, and loop as AMP and the tracking expert: `orchestrator.algos.onpolicy`) on the
reward e^(−L_g) of the state each step reaches, episodes ending early on a fall. The
actor-critic sees the state and the goal; its action is the latent offset on the frozen prior's
mean and, with σ > 0, the helper branch's pre-activation (`workers.task.policy.TaskPPOPolicy`);
its exploration is the fixed std `algo.ppo.action_std` (PULSE: 0.22 in latent units).
`algo=task` names `Task`, whose `variant` is `TaskPPO` when `algo.task.trainer=ppo` (`method_class`).

Evaluation (`orchestrator.evaluation.tasks`), the same for both trainers: the normalised return and success rate over a
fixed set of goals, the style score (the applied action's deviation from the
decoder's own, degrees) and the time until fall under the task policy. At the start
the skill stage's own evaluation is copied into this run as `skill/...`, so a
sweep over skill stages can set them beside the task's results.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from orchestrator.algos.base import Component, ReplayFed, UpdateSchedule
from orchestrator.algos.onpolicy import OnPolicy
from orchestrator.components.ppo import PPOActor
from orchestrator.components.task import TaskActor, skill_model
from orchestrator.evaluation.tasks import evaluate_task
from orchestrator.schema import MethodConfig, PPOLoop, ReplayLoop
from workers.body.features import StateLayout
from workers.learners.ppo import PPOConfig
from workers.learners.task import TaskConfig
from workers.task.policy import TaskPPOPolicy, TaskRolloutPolicy, ppo_dims


@dataclass
class TaskLoop(ReplayLoop, PPOLoop):
    """The task's loop: the model-based trainer's replay knobs and the PPO trainer's."""


@dataclass
class TaskAlgo(MethodConfig):
    task: TaskConfig = field(default_factory=TaskConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)  # the ppo trainer's (algo.task.trainer=ppo)
    loop: TaskLoop = field(default_factory=TaskLoop)


class SkillTask:
    """What both task trainers share: the frozen skill model, its evaluation copied in, the task evaluation."""

    cfg: Any
    upstream: dict[str, Any]
    skill: dict[str, Any] | None = None
    learner_key = ""  # the component whose weights are the task policy's

    def skill_payload(self) -> dict[str, Any]:
        """The frozen decoder and prior the workers and the evaluation run (downloaded once)."""
        if self.skill is None:  # with the model-based trainer, a skill model without a world model fails here
            model_based = self.cfg.algo.task.trainer == "model"
            self.skill = skill_model(self.upstream["skill"], world_model=model_based)
        return self.skill

    def configure_skill(self, trainer) -> None:
        """The workers get the frozen skill model; the skill stage's own evaluation is copied into this run."""
        skill = self.skill_payload()
        trainer.configure_workers(skill={k: skill[k] for k in ("config", "module", "prior_action")})
        copy_skill_metrics(trainer, self.upstream["skill"])

    def evaluate(self, trainer, final: bool) -> dict[str, float]:
        """The task policy (its learner's newest weights) on the skill model, by `evaluation.tasks`."""
        rt = trainer.runtime
        weights = rt.get(rt.call(trainer.handles[self.learner_key], "get_weights"))
        character, library = self.character_and_library()
        policy = self.make_policy(self.cfg, character)
        policy.configure({"skill": self.skill_payload()})
        policy.set_weights(weights)
        return evaluate_task(self.cfg, character, library, policy, trainer.logger, trainer.state.iteration, final)


class Task(SkillTask, ReplayFed):
    config_class = TaskAlgo
    needs = ("skill",)
    learner_key = "task"

    @classmethod
    def variant(cls, cfg) -> type[SkillTask]:
        return TaskPPO if cfg.algo.task.trainer == "ppo" else cls  # the other trainer is PPO's loop

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.schedule = UpdateSchedule.of(cfg, "task")

    def components(self) -> list[Component]:
        self.skill_payload()  # a skill stage that is not one fails here, before any actor starts
        b, a = self.character.num_bodies, self.character.num_actions
        return [Component("task", TaskActor, (self.cfg, b, a, self.upstream["skill"]), actor="learner-task")]

    @classmethod
    def make_policy(cls, cfg, character) -> TaskRolloutPolicy:
        return TaskRolloutPolicy(character.num_bodies, character.num_actions, cfg.algo.task, cfg.character.control_hz)

    # The iteration -----------------------------------------------------------------
    def publish(self, trainer) -> None:
        trainer.publish(trainer.runtime.get(trainer.runtime.call(trainer.handles["task"], "get_weights")))

    def start(self, trainer) -> None:
        self.configure_skill(trainer)
        super().start(trainer)

    def step(self, trainer) -> tuple[int, dict[str, float]]:
        cfg, rt, h = self.cfg, trainer.runtime, trainer.handles
        loop = cfg.algo.loop
        t0 = time.perf_counter()
        infos, collected = self.exchange(trainer, "task")
        metrics: dict[str, float] = {}
        if infos[-1]["size"] >= loop.warmup:
            m = rt.get(rt.call(h["task"], "train", self.schedule.due(collected)))
            trainer.check_alive("task", m.pop("incarnation"))
            metrics.update({f"task/{k}": float(v) for k, v in m.items()})
        self.publish(trainer)
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

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"reward": f"{metrics.get('rollout/task_reward', float('nan')):.3g}"}

    def state_dict(self) -> dict[str, Any]:
        return self.schedule.state_dict("task")

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.schedule.load_state_dict(state, "task")


class TaskPPO(SkillTask, OnPolicy):
    """A task policy trained by PPO in the simulator (`algo.task.trainer=ppo`), on the reward e^(−L_g)."""

    config_class = TaskAlgo
    needs = Task.needs
    expert = None
    learner_key = "ppo"

    def components(self) -> list[Component]:
        skill = self.skill_payload()
        task = self.cfg.algo.task
        state_dim, latent_dim = StateLayout(self.character.num_bodies).dim, skill["config"].latent_dim
        obs_dim, act_dim, helper = ppo_dims(task, state_dim, latent_dim, self.character.num_actions)
        return [Component("ppo", PPOActor, (self.cfg, obs_dim, act_dim, helper), actor="learner-ppo")]

    @classmethod
    def make_policy(cls, cfg, character) -> TaskPPOPolicy:
        return TaskPPOPolicy(
            character.num_bodies, character.num_actions, cfg.algo.task, cfg.character.control_hz, cfg.algo.ppo
        )

    def start(self, trainer) -> None:
        self.configure_skill(trainer)
        super().start(trainer)

    def step(self, trainer) -> tuple[int, dict[str, float]]:
        collected, metrics = super().step(trainer)
        if "ppo/reward_mean" in metrics:
            metrics["rollout/task_reward"] = metrics["ppo/reward_mean"]
        return collected, metrics


def copy_skill_metrics(trainer, up) -> None:
    """The skill stage's own final evaluation, as skill/... metrics of this run (once, at its start)."""
    copied = {f"skill/{k.removeprefix('eval/')}": v for k, v in up.metrics().items() if k.startswith("eval/")}
    if copied and trainer.state.iteration == 0:
        trainer.logger.log_metrics(copied, step=0)
