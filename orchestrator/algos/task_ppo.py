"""A downstream task trained by PPO in the simulator (`algo=task algo.task.trainer=ppo`).

The comparison ControlVAE draws against its model-based learner, and how PhysicsVAE
and PULSE train their task policies: PPO (the same learner, `learner-ppo`, and loop
as AMP and the tracking expert: `orchestrator.algos.onpolicy`) on the reward
e^(−L_g) of the state each step reaches, episodes ending early on a fall. The
actor-critic sees the state and the goal; its action is the latent offset on the
frozen prior's mean and, with σ > 0, the helper branch's pre-activation
(`workers.task_policy.TaskPPOPolicy`); its exploration is the fixed std
`algo.ppo.action_std` (PULSE: 0.22 in latent units). Evaluation as the model-based
trainer's (`orchestrator.algos.task`).
"""

from __future__ import annotations

from orchestrator.algos import Component
from orchestrator.algos.onpolicy import OnPolicy
from orchestrator.algos.task import Task, copy_skill_metrics
from orchestrator.components import load_world
from orchestrator.components_ppo import PPOActor
from orchestrator.evaluate_task import evaluate_task
from workers.losses.task import goal_observation_dim
from workers.sim.features import StateLayout
from workers.task_policy import TaskPPOPolicy


class TaskPPO(OnPolicy):
    sections = Task.sections
    needs = Task.needs
    skill_payload = Task.skill_payload

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.skill = None

    def components(self) -> list[Component]:
        skill = self.skill_payload()
        task = self.cfg.algo.task
        obs_dim = StateLayout(self.character.num_bodies).dim + goal_observation_dim(task.task)
        act_dim = skill["config"].latent_dim + (self.character.num_actions if task.sigma > 0 else 0)
        return [Component("ppo", PPOActor, (self.cfg, obs_dim, act_dim), actor="learner-ppo")]

    @classmethod
    def make_policy(cls, cfg, character) -> TaskPPOPolicy:
        return TaskPPOPolicy(
            character.num_bodies, character.num_actions, cfg.algo.task, cfg.character.control_hz, cfg.algo.ppo
        )

    def start(self, t) -> None:
        skill = self.skill_payload()
        t.configure_workers(skill={k: skill[k] for k in ("config", "module", "prior_action")})
        copy_skill_metrics(t, self.upstream["skill"])
        super().start(t)

    def step(self, t) -> tuple[int, dict[str, float]]:
        collected, metrics = super().step(t)
        if "ppo/reward_mean" in metrics:
            metrics["rollout/task_reward"] = metrics["ppo/reward_mean"]
        return collected, metrics

    def evaluate(self, t, final: bool) -> dict[str, float]:
        if self.world is None:
            self.world = load_world(self.cfg)
        policy = self.make_policy(self.cfg, self.world[0])
        policy.configure({"skill": self.skill_payload()})
        policy.set_weights(t.rt.get(t.rt.call(t.handles["ppo"], "get_weights")))
        return evaluate_task(self.cfg, *self.world, policy, t.tracker, t.state.iteration, final)
