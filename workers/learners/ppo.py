"""PPO with a fixed-std Gaussian policy, as AMP trains its policies (Peng et al. 2021, Sec. 6.3, Table 4).

One call of `train_on_rollout` is one PPO iteration: value estimates and GAE(λ)
advantages with TD(λ) returns are computed once for the whole rollout, then
`epochs` passes over it in shuffled minibatches, each minibatch one `update`
(one optimiser step, with the base class's non-finite checks). The observation
normaliser is updated from the rollout after those passes, so the
log-probabilities recorded while acting are those of the policy being optimised.

The defaults are AMP's Table 4 for single-clip imitation: SGD with momentum 0.9,
policy step size 2e-6, value step size 1e-4, γ = 0.95, λ = 0.95, clip 0.02,
minibatches of 256 (the paper collects 4096 samples per update; the rollout's
T × B is the caller's choice). For tasks AMP uses γ = 0.99, policy 4e-6, value 2e-5.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch

from workers.learners.base import Learner, all_finite, cpu_seeded, make_optimizer
from workers.losses.ppo import action_bound_loss, compute_gae, ppo_loss
from workers.models.actor_critic import ActorCritic, HelperActorCritic, HelperLayout
from workers.types import Trajectory


@dataclass
class PPOConfig:
    # Hidden layer sizes of the policy mean's MLP (AMP: 1024, 512).
    policy_hidden: tuple[int, ...] = (1024, 512)
    # Hidden layer sizes of the value function's MLP, a separate network (AMP: 1024, 512).
    value_hidden: tuple[int, ...] = (1024, 512)
    # Activation between hidden layers, a key of workers.models.nets.ACTIVATIONS (AMP: ReLU).
    activation: str = "relu"
    # Fixed standard deviation of the Gaussian policy, in action units. AMP fixes Σ by hand
    # and does not print it; 0.05 is our choice (ControlVAE's action noise is also 0.05).
    action_std: float = 0.05
    # Initial scale of the policy's output layer, so the first actions are close to zero.
    policy_out_scale: float = 0.01
    # The observation normaliser stops updating after this many samples.
    obs_norm_max_count: float = 1e6
    # "sgd" (with `momentum`; AMP's choice) or "adam".
    optimizer: str = "sgd"
    # SGD momentum (AMP: 0.9); unused by Adam.
    momentum: float = 0.9
    # Step size of the policy's parameters (AMP: 2e-6 single-clip imitation, 4e-6 tasks).
    policy_lr: float = 2e-6
    # Step size of the value function's parameters (AMP: 1e-4 single-clip imitation, 2e-5 tasks).
    value_lr: float = 1e-4
    # Discount (AMP: 0.95 single-clip imitation, 0.99 tasks).
    gamma: float = 0.95
    # λ of GAE(λ) for the advantages and of TD(λ) for the value targets (AMP: 0.95 for both).
    lam: float = 0.95
    # PPO clip threshold ε on the probability ratio (AMP: 0.02).
    clip: float = 0.02
    # Passes over each rollout. Not given in the AMP paper; one pass of 4096 samples is 16 steps.
    epochs: int = 1
    # Samples per optimiser step (AMP: 256).
    minibatch_size: int = 256
    # Weight of the value loss ½(V − R)² in the total; with separate step sizes per network it
    # only rescales the value step size.
    value_coef: float = 1.0
    # Maximum change of V from the acting value before its error stops counting; None: no value clipping.
    value_clip: float | None = None
    # Global gradient-norm clip per optimiser step; None: no clipping (the paper mentions none).
    grad_clip: float | None = None
    # Normalise advantages to mean 0, std 1 within each minibatch.
    normalize_advantages: bool = True
    # Soft bound on the policy mean: a penalty action_bound_coef · Σ max(|μ| − bound, 0)²
    # keeps means inside [−bound, bound]; None: unbounded. The environment clips applied actions.
    action_bound: float | None = None
    # Weight of the action-bound penalty.
    action_bound_coef: float = 10.0
    # Seeds network initialisation, minibatch shuffling and action sampling.
    seed: int = 0

    def __post_init__(self) -> None:
        self.policy_hidden = tuple(self.policy_hidden)
        self.value_hidden = tuple(self.value_hidden)
        if self.optimizer not in ("sgd", "adam"):
            raise ValueError(f"PPOConfig.optimizer must be 'sgd' or 'adam', got {self.optimizer!r}")
        if self.epochs < 1 or self.minibatch_size < 1:
            raise ValueError("PPOConfig.epochs and minibatch_size must be at least 1")
        if not (self.clip > 0 and self.action_std > 0):
            raise ValueError("PPOConfig.clip and action_std must be positive")


@dataclass
class Rollout:
    """T steps of B environments, time first. Arrays or tensors.

    Episode ends follow `workers.losses.ppo`: dones[t] = 1 when the episode ended after
    step t (row t + 1 starts the next one); truncated[t] = 1 when that end was a time
    limit, in which case final_obs[t] (the observation reached, before the reset) is
    bootstrapped from. An end without truncation is terminal.
    """

    obs: Any  # [T, B, obs_dim] observation each action was taken from
    actions: Any  # [T, B, act_dim] actions as sampled (unclipped), which log_probs refer to
    log_probs: Any  # [T, B] log π_old(action | obs) when acting
    rewards: Any  # [T, B]
    dones: Any  # [T, B] 1 where the episode ended after the step
    last_obs: Any  # [B, obs_dim] observation after the last step, bootstrapped from where it did not end
    values: Any = None  # [T, B] V(obs) when acting; recomputed with the current weights when None
    truncated: Any = None  # [T, B] 1 where the end was a time limit; None: every end is terminal
    final_obs: Any = None  # [T, B, obs_dim] observation reached after each step; required with truncated


@dataclass
class PPOBatch:
    """A flat minibatch of N samples for one optimiser step."""

    obs: torch.Tensor  # [N, obs_dim]
    actions: torch.Tensor  # [N, act_dim]
    log_probs: torch.Tensor  # [N] log π_old
    advantages: torch.Tensor  # [N] GAE(λ)
    returns: torch.Tensor  # [N] TD(λ) targets
    values: torch.Tensor  # [N] V when the advantages were computed (for value clipping)

    def __getitem__(self, idx: torch.Tensor) -> PPOBatch:
        return PPOBatch(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    def __len__(self) -> int:
        return self.log_probs.shape[0]


def build_actor_critic(
    obs_dim: int, act_dim: int, config: PPOConfig, helper: HelperLayout | None = None
) -> ActorCritic:
    """The network a PPOConfig describes (the learner, rollout workers and evaluation build it alike); with
    `helper`, a task policy with PhysicsVAE's helper branch H(s, z) (`HelperActorCritic`)."""
    c = config
    if helper is not None:
        if (obs_dim, act_dim) != (helper.obs_dim, helper.act_dim):
            raise ValueError(f"helper layout {helper} does not split observations {obs_dim} and actions {act_dim}")
        return HelperActorCritic(
            helper.state_dim, helper.goal_dim, helper.latent_dim, helper.action_dim, c.action_std,
            c.policy_hidden, c.value_hidden, helper.hidden, c.activation, c.policy_out_scale, c.obs_norm_max_count,
        )  # fmt: skip
    return ActorCritic(
        obs_dim,
        act_dim,
        action_std=c.action_std,
        policy_hidden=c.policy_hidden,
        value_hidden=c.value_hidden,
        activation=c.activation,
        policy_out_scale=c.policy_out_scale,
        obs_norm_max_count=c.obs_norm_max_count,
    )


# Metrics that are counters or settings: report the last value rather than the mean over steps.
_LAST = ("skipped_updates", "lr")


class PPOLearner(Learner):
    name = "ppo"

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        config: PPOConfig | None = None,
        device: str = "cpu",
        helper: HelperLayout | None = None,
    ):
        cfg = config if config is not None else PPOConfig()
        with cpu_seeded(cfg.seed):
            module = build_actor_critic(obs_dim, act_dim, cfg, helper)
        groups = [
            {"params": list(module.policy.parameters()), "lr": cfg.policy_lr},
            {"params": list(module.critic.parameters()), "lr": cfg.value_lr},
        ]
        options = {"momentum": cfg.momentum} if cfg.optimizer == "sgd" else {}
        optimizer = make_optimizer(cfg.optimizer, groups, cfg.policy_lr, **options)
        super().__init__(module, optimizer, cfg.grad_clip, device)
        self.module: ActorCritic
        self.config = cfg
        self._shuffle_rng = torch.Generator().manual_seed(cfg.seed)
        self._noise_rng = torch.Generator(device=self.device).manual_seed(cfg.seed + 1)

    # The step ----------------------------------------------------------------
    def loss(self, batch: PPOBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        cfg = self.config
        dist = self.module.dist(batch.obs, batch.actions)
        total, terms = ppo_loss(
            new_log_prob=dist.log_prob(batch.actions).sum(-1),
            old_log_prob=batch.log_probs,
            advantages=batch.advantages,
            values=self.module.value(batch.obs),
            returns=batch.returns,
            clip=cfg.clip,
            value_coef=cfg.value_coef,
            normalize=cfg.normalize_advantages,
            value_clip=cfg.value_clip,
            old_values=batch.values,
        )
        if cfg.action_bound is not None:
            bound = action_bound_loss(dist.mean, cfg.action_bound)
            total = total + cfg.action_bound_coef * bound
            terms["action_bound"] = bound.detach()
        return total, terms

    # One PPO iteration -------------------------------------------------------
    def train_on_rollout(self, rollout: Rollout) -> dict[str, float]:
        """GAE once, then epochs × minibatches of `update`; returns metrics averaged over the steps.

        A rollout holding any non-finite number is skipped whole (counted once in
        `skipped_updates`): neither the weights nor the normaliser see it.
        """
        cfg = self.config
        r = {f.name: self._tensor(getattr(rollout, f.name)) for f in fields(rollout)}
        if (r["truncated"] is None) != (r["final_obs"] is None):
            raise ValueError("Rollout.truncated and Rollout.final_obs come together")
        if not all_finite(v for v in r.values() if v is not None):
            return self._skip({"rollout_skipped": 1.0})
        obs, rewards = r["obs"], r["rewards"]
        steps, envs = rewards.shape
        with torch.no_grad():
            values = r["values"] if r["values"] is not None else self.module.value(obs)
            next_values = None
            if r["final_obs"] is not None:  # V of the observations reached at time limits only
                next_values = torch.zeros_like(rewards)
                cut = r["truncated"] > 0
                if bool(cut.any()):
                    next_values[cut] = self.module.value(r["final_obs"][cut])
            advantages, returns = compute_gae(
                rewards,
                values,
                r["dones"],
                self.module.value(r["last_obs"]),
                cfg.gamma,
                cfg.lam,
                truncations=r["truncated"],
                next_values=next_values,
            )
        n = steps * envs
        data = PPOBatch(
            obs=obs.reshape(n, -1),
            actions=r["actions"].reshape(n, -1),
            log_probs=r["log_probs"].reshape(n),
            advantages=advantages.reshape(n),
            returns=returns.reshape(n),
            values=values.reshape(n),
        )
        sums: dict[str, float] = defaultdict(float)
        counts: dict[str, int] = defaultdict(int)
        last: dict[str, float] = {}
        for _ in range(cfg.epochs):
            order = torch.randperm(n, generator=self._shuffle_rng).to(self.device)
            for start in range(0, n, cfg.minibatch_size):
                for k, v in self.update(data[order[start : start + cfg.minibatch_size]]).items():
                    if k in _LAST:
                        last[k] = v
                    else:
                        sums[k] += v
                        counts[k] += 1
        self.module.obs_norm.update(obs)
        metrics = {k: sums[k] / counts[k] for k in sums} | last
        with torch.no_grad():
            residual_var = torch.var(returns - values)
            metrics["explained_variance"] = float(1.0 - residual_var / torch.var(returns).clamp(min=1e-8))
        metrics["advantage_mean"] = float(advantages.mean())
        metrics["return_mean"] = float(returns.mean())
        metrics["reward_mean"] = float(rewards.mean())
        return metrics

    # Acting ------------------------------------------------------------------
    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """[B, obs_dim] -> (actions [B, act_dim], log_probs [B], values [B]), float32 numpy arrays.

        Samples with the learner's own seeded generator; `deterministic` returns the mean action.
        """
        o = self._tensor(obs)
        actions, log_probs = self.module.act(o, deterministic=deterministic, generator=self._noise_rng)
        values = self.module.value(o)
        return actions.cpu().numpy(), log_probs.cpu().numpy(), values.cpu().numpy()

    # Checkpoints -------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state["shuffle_rng"] = self._shuffle_rng.get_state()
        state["noise_rng"] = self._noise_rng.get_state()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self._shuffle_rng.set_state(state["shuffle_rng"])
        try:
            self._noise_rng.set_state(state["noise_rng"])
        except RuntimeError:  # saved on another device's generator: acting noise starts from this one's seed
            pass

    def _tensor(self, x: Any) -> torch.Tensor | None:
        return None if x is None else self.tensor(x)


def ppo_rollout(trajs: tuple[Trajectory, ...], rewards: list[np.ndarray] | None) -> Rollout:
    """The workers' trajectories side by side (environments concatenated) as one PPO rollout [T, ΣM]."""

    def cat(key: str) -> np.ndarray:
        return np.concatenate([tr.extras[key] for tr in trajs], axis=1)

    obs = cat("obs")
    final = np.zeros_like(obs)
    offset = 0
    for tr in trajs:
        rows = tr.extras["final_rows"]
        final[rows[:, 0], offset + rows[:, 1]] = tr.extras["final_obs"]
        offset += tr.done.shape[1]
    reward = np.concatenate(rewards, axis=1) if rewards is not None else cat("reward")
    return Rollout(
        obs=obs,
        actions=cat("action"),  # the policy's samples (PD targets, or offsets for a residual policy)
        log_probs=cat("log_prob"),
        rewards=reward,
        dones=np.concatenate([tr.done for tr in trajs], axis=1).astype(np.float32),
        last_obs=np.concatenate([tr.extras["last_obs"] for tr in trajs], axis=0),
        values=None,  # V(o) of the whole rollout in one batch, by the learner before it updates
        truncated=cat("truncated").astype(np.float32),
        final_obs=final,
    )
