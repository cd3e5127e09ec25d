"""The task policy on a frozen skill decoder, as a rollout worker runs it.

`TaskRolloutPolicy` is a `Policy` and a `Recorder` at once: it keeps every
environment's goal (`workers.task.goals.GoalSampler`: drawn when an episode starts,
redrawn within it at the task's change rate, part of the policy's input), acts
with z around μ_p(s) + μ_g(s, g) and the frozen decoder (plus the helper branch
when σ > 0), and records per step the goal it acted for (`goal`), the task reward
of the state it reached (`reward`: e^(−L_g), or with `reward: progress` the point goal's
d_{t−1} − d_t; each term under `reward/<term>`),
and the helper's mean absolute deviation from the decoder's own action
(`helper_deviation`, radians).

The frozen skill model (the decoder, its prior and the VAE config that builds
them) arrives once through `configure({"skill": ...})`; the task policy's own
weights arrive with every version through `set_weights`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from workers.learners.base import Weights
from workers.learners.task import TaskConfig, task_policy
from workers.learners.vae import build_controller
from workers.losses.task import task_terms
from workers.models import body_state
from workers.models.actor_critic import HelperLayout
from workers.models.nets import gaussian
from workers.models.task import goal_observation, goal_observation_dim
from workers.policies import Policy
from workers.recorders import Recorder, record_buffer, to_host
from workers.sim.env import Simulator, StepResult
from workers.task.goals import GoalSampler


def helper_layout(config: TaskConfig, state_dim: int, latent_dim: int, action_dim: int) -> HelperLayout | None:
    """How PPO splits a task policy with the helper branch (σ > 0) into μ_g(s, g) and H(s, z)
    (`workers.models.actor_critic.HelperActorCritic`); None without the branch."""
    if config.sigma <= 0:
        return None
    goal_dim = goal_observation_dim(config.task)
    return HelperLayout(state_dim, goal_dim, latent_dim, action_dim, tuple(config.helper_hidden))


def ppo_dims(
    config: TaskConfig, state_dim: int, latent_dim: int, action_dim: int
) -> tuple[int, int, HelperLayout | None]:
    """(observation size, action size, helper layout or None) of the task policy PPO trains: (s, g) → u_z, or
    with the helper branch (s, g, b) → (u_z, u_h)."""
    helper = helper_layout(config, state_dim, latent_dim, action_dim)
    if helper is None:
        return state_dim + goal_observation_dim(config.task), latent_dim, None
    return helper.obs_dim, helper.act_dim, helper


def skill_controller(skill: dict[str, Any], num_bodies: int, action_dim: int) -> torch.nn.Module:
    """The frozen VAE controller of a skill payload {"config": VAEConfig, "module": state dict, ...}."""
    controller = build_controller(num_bodies, action_dim, skill["config"])
    controller.load_state_dict(skill["module"])
    return controller.eval().requires_grad_(False)


class TaskRolloutPolicy(Policy, Recorder):
    reads_device_states = True

    def __init__(self, num_bodies: int, action_dim: int, config: TaskConfig, control_hz: float, stochastic=True):
        self.num_bodies, self.action_dim = num_bodies, action_dim
        self.config, self.control_hz = config, control_hz
        self.stochastic = stochastic and config.latent_noise
        self.controller: torch.nn.Module | None = None
        self.module: torch.nn.Module | None = None
        self.weights: Weights | None = None

    def networks(self) -> list[torch.nn.Module]:
        return [net for net in (self.controller, self.module) if net is not None]

    def bind(self, num_envs: int, rng: np.random.Generator, generator: torch.Generator) -> None:
        super().bind(num_envs, rng, generator)
        self.goals = GoalSampler(self.config.task, num_envs, self.control_hz, self.config.change_rate, rng)
        self.unset = np.arange(num_envs)  # environments whose goals are drawn at the next act

    def configure(self, settings: dict[str, Any]) -> None:
        if "skill" not in settings:
            return
        skill = settings["skill"]
        self.controller = skill_controller(skill, self.num_bodies, self.action_dim).to(self.device)
        module = task_policy(self.controller, self.action_dim, self.config, skill.get("prior_action", True))
        self.module = module.eval().requires_grad_(False).to(self.device)
        if self.weights is not None:
            self.module.load_state_dict(self.weights.state)

    def set_weights(self, weights: Weights) -> None:
        self.weights = weights
        self.version = int(weights.version)
        if self.module is not None:
            self.module.load_state_dict(weights.state)

    def actions(self, sim: Simulator, bs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(applied actions [M, A], the decoder's own actions [M, A]) for body states bs [M, B, 13]."""
        applied, decoded = self._actions_on(sim, bs)
        return applied.cpu().numpy(), decoded.cpu().numpy()

    @torch.no_grad()
    def _actions_on(self, sim: Simulator, bs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`actions` on the policy's device."""
        if self.module is None:
            raise RuntimeError("the task policy has no skill model yet (configure({'skill': ...}) first)")
        self._start_step(sim, bs)
        b = self.tensor(bs)
        s = body_state.features(b)
        obs = goal_observation(self.config.task, b, self.tensor(self.goals.goals))
        eps = None
        if self.stochastic:
            eps = gaussian((len(bs), self.controller.latent_dim), self.generator, device=self.device)
        applied, decoded, _ = self.module.act(self.controller, s, obs, eps)
        return applied, decoded

    def _start_step(self, sim: Simulator, bs: np.ndarray | torch.Tensor) -> None:
        """Before acting on body states bs: draw the goals not drawn yet and, for the progress reward, keep the
        distance the step starts from, d_{t−1} (where bs is: on the host, or on the simulator's device)."""
        if len(self.unset):
            self.goals.reset(sim, bs, self.unset)
            self.unset = self.unset[:0]
        if self.config.reward == "progress":
            b = torch.as_tensor(bs)
            goals = torch.as_tensor(self.goals.goals, device=b.device)
            self.before = task_terms(self.config.task, b, goals)["distance"]

    def act(self, sim: Simulator, bs: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        applied, decoded = self._actions_on(sim, bs)
        extras = {"goal": self.goals.goals.copy(), "helper_deviation": _deviation(sim, applied, decoded)}
        return self.output(sim, applied), extras

    # Recorder: the task reward of each step, for the goal the step was taken for ------------
    # Beside a simulator that computes on its device, the reward and its terms are computed and kept there (the
    # goals [M, G] are copied there each step); the worker copies them to the host once per collect.
    def begin(self, steps: int, num_envs: int, sim: Simulator) -> None:
        self.reward = record_buffer((steps, num_envs), sim)
        self.terms: dict[str, np.ndarray | torch.Tensor] = {}

    def record(self, t: int, sim: Simulator, result: StepResult) -> None:
        on_device = sim.computes_on_device
        bs = result.on_device.body_states if on_device else torch.from_numpy(result.body_states)
        terms = task_terms(self.config.task, bs, torch.as_tensor(self.goals.goals, device=bs.device))
        if self.config.reward == "progress":
            self.reward[t] = self.before - terms["distance"]
        else:
            loss = sum(self.config.weights[k] * v for k, v in terms.items())
            self.reward[t] = torch.exp(-loss) if on_device else np.exp(-loss.numpy())
        for k, v in terms.items():
            if k not in self.terms:
                self.terms[k] = record_buffer(tuple(self.reward.shape), sim)
            self.terms[k][t] = v
        self.goals.advance(sim, bs if on_device else bs.numpy())

    def after_reset(self, sim: Simulator, ids: np.ndarray) -> None:
        self.goals.reset(sim, sim.device_body_states() if sim.computes_on_device else sim.body_states(), ids)

    def finish(self) -> dict[str, np.ndarray]:
        return {"reward": to_host(self.reward), **{f"reward/{k}": to_host(v) for k, v in self.terms.items()}}

    def state_dict(self) -> dict[str, Any]:
        return {"goals": self.goals.state_dict(), "unset": self.unset.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.goals.load_state_dict(state["goals"])
        self.unset = np.asarray(state["unset"], np.int64).copy()


class TaskPPOPolicy(TaskRolloutPolicy):
    """The task policy as PPO trains it in the simulator: a Gaussian actor-critic on (s, goal) whose action u
    is the latent offset μ_g (Z) and, with σ > 0, the helper's pre-activation h (A); the applied action is
    D(s, μ_p(s) + u_z) + σ·tanh(u_h). Its extras are PPO's (observation, u, log π(u | o)) and the task's."""

    observes = True

    def __init__(self, num_bodies: int, action_dim: int, config: TaskConfig, control_hz: float, ppo_config):
        super().__init__(num_bodies, action_dim, config, control_hz)
        self.ppo_config = ppo_config
        self.prior_action = True
        self.helper: HelperLayout | None = None

    def configure(self, settings: dict[str, Any]) -> None:
        from workers.learners.ppo import build_actor_critic

        if "skill" not in settings:
            return
        skill = settings["skill"]
        self.controller = skill_controller(skill, self.num_bodies, self.action_dim).to(self.device)
        self.prior_action = bool(skill.get("prior_action", True))
        state_dim, latent_dim = self.controller.state_norm.mean.shape[0], self.controller.latent_dim
        obs_dim, act_dim, self.helper = ppo_dims(self.config, state_dim, latent_dim, self.action_dim)
        module = build_actor_critic(obs_dim, act_dim, self.ppo_config, self.helper)
        self.module = module.eval().requires_grad_(False).to(self.device)
        if self.weights is not None:
            self.module.load_state_dict(self.weights.state)

    def observe(self, sim: Simulator, bs: np.ndarray) -> np.ndarray:
        return self._observation(sim, bs).cpu().numpy()

    def _observation(self, sim: Simulator, bs: np.ndarray | torch.Tensor) -> torch.Tensor:
        """The observation (s, g[, b]) on the policy's device."""
        self._start_step(sim, bs)
        b = self.tensor(bs)
        s = body_state.features(b)
        parts = [s, goal_observation(self.config.task, b, self.tensor(self.goals.goals))]
        if self.helper is not None:  # the latent u_z is added to, for the helper's z = b + u_z
            parts.append(
                self.controller.prior_dist(s).mean if self.prior_action else s.new_zeros(len(s), self.helper.latent_dim)
            )
        return torch.cat(parts, dim=-1)

    @torch.no_grad()
    def decode(self, bs: np.ndarray | torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(applied, decoder's own) actions [M, A] for the PPO action u [M, Z (+ A)], on the policy's device."""
        s = body_state.features(self.tensor(bs))
        latent = self.controller.latent_dim
        z = u[:, :latent] + (self.controller.prior_dist(s).mean if self.prior_action else 0.0)
        decoded = self.controller.act(s, z)
        applied = decoded + self.config.sigma * torch.tanh(u[:, latent:]) if self.config.sigma > 0 else decoded
        return applied, decoded

    @torch.no_grad()
    def _actions_on(self, sim: Simulator, bs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.module is None:
            raise RuntimeError("the task policy has no skill model yet (configure({'skill': ...}) first)")
        return self.decode(bs, self.module.mean(self._observation(sim, bs)))

    @torch.no_grad()
    def act(self, sim: Simulator, bs: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        obs = self._observation(sim, bs)
        u, log_prob = self.module.act(obs, generator=self.generator)
        applied, decoded = self.decode(bs, u)
        extras = {k: self.output(sim, v) for k, v in (("obs", obs), ("action", u), ("log_prob", log_prob))}
        extras |= {"goal": self.goals.goals.copy(), "helper_deviation": _deviation(sim, applied, decoded)}
        return self.output(sim, applied), extras


def _deviation(sim: Simulator, applied: torch.Tensor, decoded: torch.Tensor) -> np.ndarray | torch.Tensor:
    """[M] float32 each environment's mean |applied − decoded| (radians): the helper's deviation from the decoder,
    computed where the actions are kept (on the simulator's device beside one that computes there)."""
    if sim.computes_on_device:
        return (applied - decoded).abs().mean(-1)
    return np.abs(applied.cpu().numpy() - decoded.cpu().numpy()).mean(-1).astype(np.float32)
