"""The policies a rollout worker can run, behind one small interface.

A `Policy` maps the simulator's current state to actions for all M environments
at once, and returns with them the per-environment numbers its learner needs
(observations, samples and log-probabilities for PPO, nothing for the VAE controller). The
worker hands each policy its random streams (`bind`), so one seed gives the same
trajectories whichever process runs the worker.

- `VAEPolicy`: ControlVAE's collection (§3.4, Alg. 1). Each episode tracks its
  clip with z from the posterior q(z | s_t, s̃_{t+1}) or, with probability
  `prior_probability`, from the prior p(z | s_t) at every step; the action is the
  policy's mean plus Gaussian noise of std `action_noise` (σ_π).
- `ExpertPolicy`: an expert (or one per clip, mirrored on mirrored clips) with action noise: the demos.
- `GaussianPolicy`: the PPO actor-critic, π(a | o) = N(μ(o), σ²) with fixed σ, acting on
  the observation `obs`: "state" (s, AMP's policy input for single-clip imitation),
  "imitation" (s and the reference's s̃_{t+1}, the tracking expert's) or "mimic" (s and
  PULSE's s_g-mimic, the reference's next state as offsets from the character:
  `workers.models.tracking_goal`). With `residual`, the sampled action is an offset from the
  reference's next pose (the PD targets that hold it), as tracking controllers commonly
  act: the untrained policy then starts as PD tracking of the clip rather than holding
  the zero pose, which earns no imitation reward at all. The trajectory's `actions` are
  always the PD targets applied; the sample that the log-probability refers to is the
  extra `action`.

Inference runs batched, in eval mode and without gradients, on the policy's `device` (`Policy.to`;
the rollout worker puts it on its simulator's device, a GPU with MuJoCo Warp on CUDA): the
networks live there and their inputs are copied there. The actions and extras come back to the host
as NumPy, except beside a simulator that computes on its device (MuJoCo Warp,
`Simulator.computes_on_device`): there they stay tensors on the device, the simulator takes the
actions there and the worker keeps both until its collect ends. The noise is drawn from the
worker's CPU generator and then moved (`workers.models.nets.gaussian`), so a seed gives the same
draws on either device and the worker's checkpoint holds one random stream.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from workers.learners.base import Weights, cpu_seeded
from workers.learners.vae import VAEConfig, build_controller
from workers.models import body_state
from workers.models.actor_critic import ActorCritic
from workers.models.deploy import ActorMean, PriorMeanController
from workers.models.nets import gaussian
from workers.models.tracking_goal import goal_dim
from workers.rewards import imitation_observation
from workers.sim.env import Simulator

OBSERVATIONS = ("state", "imitation", "mimic")
EXPERT_KINDS = ("ppo", "vae")


def observation_dim(kind: str, state_dim: int) -> int:
    """The size of observation `kind` for states s of size state_dim (`StateLayout.dim`, 16·B + 3)."""
    if kind not in OBSERVATIONS:
        raise ValueError(f"unknown observation {kind!r}; expected one of {OBSERVATIONS}")
    if kind == "mimic":
        return state_dim + goal_dim("mimic", (state_dim - 3) // 16)
    return state_dim if kind == "state" else 2 * state_dim


def observe(kind: str, sim: Simulator, bs: np.ndarray) -> np.ndarray:
    """The observation [M, D] of the environments in body states bs [M, B, 13] at their current frames.

    s is computed in NumPy (`body_state.features_np`, as the gym adapter does).
    """
    s = body_state.features_np(bs)
    if kind == "state":
        return s
    if kind == "imitation":
        return imitation_observation(s, sim.reference_next_features())
    g = sim.tracking_goal("mimic", bs).numpy()
    return np.concatenate((s, g), axis=-1).astype(np.float32)


def observe_on(device: torch.device, kind: str, sim: Simulator, bs: np.ndarray) -> torch.Tensor:
    """`observe` computed in torch on `device` (float32; the same numbers to float rounding): what a policy
    beside a simulator that computes on its device (`Simulator.computes_on_device`) observes."""
    b = torch.as_tensor(bs).to(device)
    s = body_state.features(b)
    if kind == "state":
        return s
    return torch.cat((s, sim.tracking_goal("reference" if kind == "imitation" else "mimic", b).to(device)), dim=-1)


class Policy:
    """The interface the rollout worker drives. `version` is the published weights' version (-1: none yet)."""

    version: int = -1
    # The policy acts on an observation (`observe`): the worker records the last one of each
    # collect call and the final one of each truncated episode, for bootstrapping.
    observes: bool = False
    # Where inference runs (`to`).
    device: torch.device = torch.device("cpu")
    # `act` and `observe` take body states as a tensor on the simulator's device as well as NumPy: the worker
    # then keeps them there beside a simulator that computes on its device (`Simulator.computes_on_device`).
    reads_device_states: bool = False

    def to(self, device: torch.device | str) -> Policy:
        """Run inference on `device`: the networks move there now, and those made later (an expert's or a
        skill model's, with their weights) are made there."""
        self.device = torch.device(device)
        for net in self.networks():
            net.to(self.device)
        return self

    def networks(self) -> list[torch.nn.Module]:
        """The modules inference runs through (what `to` moves)."""
        return []

    def tensor(self, array: np.ndarray) -> torch.Tensor:
        """`array` as a tensor on the policy's device (shared with NumPy on the CPU, a copy elsewhere)."""
        return torch.as_tensor(array).to(self.device)

    def bind(self, num_envs: int, rng: np.random.Generator, generator: torch.Generator) -> None:
        """Take the worker's random streams (NumPy for per-episode choices, torch for noise)."""
        self.rng, self.generator = rng, generator

    def set_weights(self, weights: Weights) -> None:
        raise NotImplementedError

    def act(self, sim: Simulator, bs: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(actions [M, A], per-environment extras {name: [M, ...]}) for body states bs [M, B, 13]. NumPy, or
        beside a simulator that computes on its device, the actions and any extra may be tensors on the
        policy's device (`Simulator.step` takes them there; the worker keeps them there until the collect
        ends)."""
        raise NotImplementedError

    @staticmethod
    def output(sim: Simulator, t: torch.Tensor) -> np.ndarray | torch.Tensor:
        """What `act` returns of a tensor t it made: t itself beside a simulator that computes on its device,
        else t as NumPy."""
        return t if sim.computes_on_device else t.cpu().numpy()

    def observe(self, sim: Simulator, bs: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def episodes_reset(self, ids: np.ndarray) -> None:
        """Environments `ids` start new episodes."""

    def deployable(self, sim: Simulator, bs: np.ndarray) -> tuple[torch.nn.Module, np.ndarray] | None:
        """(The trained policy as a module from an input batch to deterministic actions, that input for
        body states bs), for export (`workers.models.deploy`); None for a policy that is not exported."""
        return None

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass


class VAEPolicy(Policy):
    reads_device_states = True

    def __init__(self, num_bodies: int, action_dim: int, config: VAEConfig, prior_probability: float = 0.4):
        if not 0.0 <= prior_probability <= 1.0:
            raise ValueError(f"prior_probability must be in [0, 1], got {prior_probability}")
        if config.action_noise < 0:
            raise ValueError(f"action_noise must be non-negative, got {config.action_noise}")
        self.prior_probability = prior_probability
        self.action_noise = config.action_noise
        # Built under a fixed seed so that a worker that has not received weights yet is
        # deterministic too (and identical across workers).
        with cpu_seeded(0):
            self.controller = build_controller(num_bodies, action_dim, config)
        self.controller.eval().requires_grad_(False)

    def networks(self) -> list[torch.nn.Module]:
        return [self.controller]

    def bind(self, num_envs: int, rng: np.random.Generator, generator: torch.Generator) -> None:
        super().bind(num_envs, rng, generator)
        self.use_prior = self.rng.random(num_envs) < self.prior_probability  # [M] per episode

    def set_weights(self, weights: Weights) -> None:
        self.controller.load_state_dict(weights.state)
        self.version = int(weights.version)

    @torch.no_grad()
    def act(self, sim: Simulator, bs: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        s = body_state.features(self.tensor(bs))
        posterior, prior = self.controller.encode(s, sim.tracking_goal(self.controller.goal, bs).to(self.device))
        use_prior = self.tensor(self.use_prior)[:, None]
        mean = torch.where(use_prior, prior.mean, posterior.mean)
        log_std = torch.where(use_prior, prior.log_std, posterior.log_std)
        z = mean + log_std.exp() * gaussian(mean.shape, self.generator, device=self.device)
        a = self.controller.act(s, z)
        a = a + self.action_noise * gaussian(a.shape, self.generator, device=self.device)
        return self.output(sim, a), {}

    def episodes_reset(self, ids: np.ndarray) -> None:
        self.use_prior[ids] = self.rng.random(len(ids)) < self.prior_probability

    def deployable(self, sim: Simulator, bs: np.ndarray) -> tuple[torch.nn.Module, np.ndarray]:
        return PriorMeanController(self.controller), body_state.features(torch.from_numpy(bs)).numpy()

    def state_dict(self) -> dict[str, Any]:
        return {"use_prior": self.use_prior.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.use_prior = np.asarray(state["use_prior"], bool).copy()


class GaussianPolicy(Policy):
    """The PPO actor-critic; its extras are the observation, the sampled action and log π(a | o) of each step."""

    observes = True
    reads_device_states = True

    def __init__(self, module: ActorCritic, obs: str = "state", residual: bool = False):
        observation_dim(obs, 0)  # checks the name
        self.module = module.eval().requires_grad_(False)
        self.obs = obs
        self.residual = residual

    def networks(self) -> list[torch.nn.Module]:
        return [self.module]

    def base_action(self, sim: Simulator) -> np.ndarray:
        """The PD targets [M, A] that hold the reference's next pose (the zero offset of a residual policy)."""
        return sim.library.pd_targets(sim.clip_id, sim.start_frame + sim.steps + 1)

    def _base_action_on(self, sim: Simulator) -> torch.Tensor:
        """`base_action` on the policy's device (looked up there beside a simulator that computes on its device)."""
        if sim.computes_on_device:
            return sim.device_reference().pd_targets(sim.clip_id, sim.start_frame + sim.steps + 1).to(self.device)
        return self.tensor(self.base_action(sim))

    def set_weights(self, weights: Weights) -> None:
        self.module.load_state_dict(weights.state)
        self.version = int(weights.version)

    def observe(self, sim: Simulator, bs: np.ndarray) -> np.ndarray:
        return self._observation(sim, bs).cpu().numpy()

    def _observation(self, sim: Simulator, bs: np.ndarray) -> torch.Tensor:
        """The observation on the policy's device: made there beside a simulator that computes on its device."""
        if sim.computes_on_device:
            return observe_on(self.device, self.obs, sim, bs)
        return self.tensor(observe(self.obs, sim, bs))

    @torch.no_grad()
    def act(self, sim: Simulator, bs: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        obs = self._observation(sim, bs)
        actions, log_probs = self.module.act(obs, generator=self.generator)
        # V(o) is left to the learner, which evaluates it in one batch over the whole rollout.
        extras = {k: self.output(sim, v) for k, v in (("obs", obs), ("action", actions), ("log_prob", log_probs))}
        applied = actions + self._base_action_on(sim) if self.residual else actions
        return self.output(sim, applied), extras

    def deployable(self, sim: Simulator, bs: np.ndarray) -> tuple[torch.nn.Module, np.ndarray]:
        return ActorMean(self.module), self.observe(sim, bs)

    @torch.no_grad()
    def mean_on_device(self, sim: Simulator, bs: np.ndarray) -> torch.Tensor:
        """The deterministic PD targets [M, A] on the policy's device."""
        mean = self.module.mean(self._observation(sim, bs))
        return mean + self._base_action_on(sim) if self.residual else mean

    def mean_action(self, sim: Simulator, bs: np.ndarray) -> np.ndarray:
        """The deterministic PD targets [M, A] (evaluation)."""
        return self.mean_on_device(sim, bs).cpu().numpy()


def expert_module(expert: dict[str, Any], num_bodies: int, action_dim: int) -> ActorCritic:
    """The PPO actor-critic of an expert's weights payload (`ExpertPolicy`'s "ppo" kind), in eval mode."""
    from workers.body.features import StateLayout
    from workers.learners.ppo import build_actor_critic

    obs_dim = observation_dim(expert["observation"], StateLayout(num_bodies).dim)
    module = build_actor_critic(obs_dim, action_dim, expert["config"])
    module.load_state_dict(expert["module"])
    return module.eval().requires_grad_(False)


class ExpertPolicy(Policy):
    """An expert's deterministic action plus Gaussian noise of std `noise` (PhysicsVAE's demos: ε = 0.05).

    The expert's network comes with its weights: `Weights.state` is {"kind": "ppo" | "vae", "config":
    its learner config, "module": its state dict} and, for "ppo", "observation" and "residual". A PPO
    expert acts with its mean (on a residual expert, offset from the reference's next pose); a VAE
    expert (ControlVAE's posterior) with z = μ_q(s, s̃_{t+1}).

    One expert per clip (PhysicsVAE §5.1.1, "per_clip"): {"kind": "per_clip", "experts": [payloads],
    "clip_expert": [the expert of each library clip], "clip_mirrored": [whether it runs mirrored], "mirror":
    the character's index maps, `workers.body.mirror.mirror_maps`, where any clip runs mirrored}. An
    environment is driven by its clip's expert; on a mirrored clip by the original's expert mirrored,
    M∘π∘M (`workers.body.mirror`): it sees the reflected observation and its offset from the reference is
    reflected back, which on our symmetric character is the reflection of the original's rollout.
    """

    reads_device_states = True

    def __init__(self, num_bodies: int, action_dim: int, noise: float = 0.05):
        if noise < 0:
            raise ValueError(f"noise must be non-negative, got {noise}")
        self.num_bodies, self.action_dim, self.noise = num_bodies, action_dim, noise
        self.experts: list[GaussianPolicy | torch.nn.Module] = []
        self.clip_expert: np.ndarray | None = None  # per library clip; None: one expert for every clip
        self.clip_mirrored: np.ndarray | None = None
        self.mirror: tuple[torch.Tensor, ...] | None = None  # observation and action index maps, when mirroring

    def to(self, device: torch.device | str) -> ExpertPolicy:
        super().to(device)
        for e in self.experts:
            e.to(self.device)
        if self.mirror is not None:
            self.mirror = tuple(t.to(self.device) for t in self.mirror)
        return self

    def networks(self) -> list[torch.nn.Module]:
        return [n for e in self.experts for n in (e.networks() if isinstance(e, GaussianPolicy) else [e])]

    def _build(self, w: dict[str, Any]) -> GaussianPolicy | torch.nn.Module:
        if w["kind"] == "ppo":
            module = expert_module(w, self.num_bodies, self.action_dim)
            return GaussianPolicy(module, w["observation"], w["residual"]).to(self.device)
        if w["kind"] == "vae":
            controller = build_controller(self.num_bodies, self.action_dim, w["config"])
            controller.load_state_dict(w["module"])
            return controller.eval().requires_grad_(False).to(self.device)
        raise ValueError(f"unknown expert kind {w['kind']!r}; expected one of {(*EXPERT_KINDS, 'per_clip')}")

    def set_weights(self, weights: Weights) -> None:
        w = weights.state
        if w["kind"] == "per_clip":
            self.experts = [self._build(e) for e in w["experts"]]
            self.clip_expert = np.asarray(w["clip_expert"], int)
            self.clip_mirrored = np.asarray(w["clip_mirrored"], bool)
            if self.clip_mirrored.any():
                self._check_mirrorable(w["mirror"])
        else:
            self.experts, self.clip_expert, self.clip_mirrored = [self._build(w)], None, None
        self.version = int(weights.version)

    def _check_mirrorable(self, maps: dict[str, np.ndarray]) -> None:
        for e in self.experts:
            if not isinstance(e, GaussianPolicy) or e.obs not in ("state", "imitation"):
                raise ValueError("only a PPO expert observing s (and the reference's s̃_{t+1}) can be run mirrored")
        d = len(maps["feature_index"])
        obs_index = np.concatenate((maps["feature_index"], maps["feature_index"] + d))
        obs_sign = np.concatenate((maps["feature_sign"], maps["feature_sign"]))
        arrays = (obs_index, obs_sign.astype(np.float32), maps["action_index"], maps["action_sign"].astype(np.float32))
        self.mirror = tuple(torch.as_tensor(np.asarray(m)).to(self.device) for m in arrays)

    @torch.no_grad()
    def _mean(self, expert: GaussianPolicy | torch.nn.Module, sim: Simulator, bs: np.ndarray) -> torch.Tensor:
        """One expert's deterministic PD targets [M, A] for every environment."""
        if isinstance(expert, GaussianPolicy):
            return expert.mean_on_device(sim, bs)
        s = body_state.features(self.tensor(bs))
        posterior, _ = expert.encode(s, sim.tracking_goal(expert.goal, bs).to(self.device))
        return expert.act(s, posterior.mean)

    @torch.no_grad()
    def _mirrored_mean(self, expert: GaussianPolicy, sim: Simulator, bs: np.ndarray) -> torch.Tensor:
        """M∘π∘M: the expert on the reflected observation, its offset reflected back onto this clip's reference."""
        obs_index, obs_sign, act_index, act_sign = self.mirror
        obs = expert._observation(sim, bs)
        offset = expert.module.mean(obs[:, obs_index[: obs.shape[1]]] * obs_sign[: obs.shape[1]])
        offset = offset[:, act_index] * act_sign
        return offset + expert._base_action_on(sim) if expert.residual else offset

    @torch.no_grad()
    def mean_on_device(self, sim: Simulator, bs: np.ndarray) -> torch.Tensor:
        """The expert's deterministic PD targets [M, A] on the policy's device: each environment its clip's."""
        if not self.experts:
            raise RuntimeError("the expert has no weights yet")
        if self.clip_expert is None:
            return self._mean(self.experts[0], sim, bs)
        clip_id = np.asarray(sim.clip_id)
        which, mirrored = self.clip_expert[clip_id], self.clip_mirrored[clip_id]
        out = None
        for k in np.unique(which):
            for flip in (False, True):
                rows = np.flatnonzero((which == k) & (mirrored == flip))
                if not len(rows):
                    continue
                e = self.experts[k]
                mean = self._mirrored_mean(e, sim, bs) if flip else self._mean(e, sim, bs)
                if out is None:
                    out = torch.empty_like(mean)
                index = torch.as_tensor(rows, device=mean.device)
                out[index] = mean[index]
        return out

    def mean_action(self, sim: Simulator, bs: np.ndarray) -> np.ndarray:
        return self.mean_on_device(sim, bs).cpu().numpy()

    def act(self, sim: Simulator, bs: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        a = self.mean_on_device(sim, bs)
        a = a + self.noise * gaussian(a.shape, self.generator, device=self.device)
        return self.output(sim, a), {}
