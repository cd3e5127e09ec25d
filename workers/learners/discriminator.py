"""The AMP discriminator learner (Peng et al. 2021, Sec. 5 and 6.3; Table 4).

One `update` is one optimiser step on the objective of AMP Eq. 8: a
least-squares (or cross-entropy) classification of data against policy
transitions plus a gradient penalty on the data samples. The policy side
mixes the fresh batch with transitions replayed from past updates (AMP's
discriminator replay buffer B), which keeps the discriminator from
overfitting to the latest policy.

`reward` turns the discriminator into the policy's style reward (Eq. 7), and `amp_reward` mixes it with a task
reward (Eq. 4). The data: every pair of consecutive reference frames (`reference_transitions`) against the
policy's (`policy_transitions`), each as (Φ(s), Φ(s')).

Checkpoints: `state_dict()` holds the network (with its normaliser), the
optimiser and the counters, not the replay or its sampler; a resumed learner
starts with an empty replay, which refills within a few updates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from workers.body.character import Character
from workers.body.features import amp_features
from workers.learners.base import Learner, all_finite, cpu_seeded, make_optimizer
from workers.losses.discriminator import (
    check_loss_type,
    discriminator_loss,
    gradient_penalty,
    logit_regularization,
    style_reward,
)
from workers.models.discriminator import Discriminator
from workers.motion.library import MotionLibrary
from workers.types import Trajectory

GP_ON = ("data", "data_and_policy")
GP_FEATURES = ("normalised", "raw")
DISC_OPTIMIZERS = ("adam", "sgd")


@dataclass
class DiscriminatorConfig:
    # Hidden layer sizes of the discriminator MLP; AMP Sec. 6.2 uses (1024, 512).
    hidden: tuple[int, ...] = (1024, 512)
    # Hidden activation, a name from workers.models.nets.ACTIVATIONS; AMP uses ReLU.
    activation: str = "relu"
    # Skill classes the discriminator is conditioned on (ControlVAE Eq. 27); 0 for an unconditioned prior.
    num_skills: int = 0
    # 0 feeds the skill as a one-hot vector; > 0 through a learned embedding of this size.
    skill_embed_dim: int = 0
    # "lsgan" (AMP Eq. 6-7: targets +1/-1, reward max(0, 1 - 0.25 (D-1)²)) or "bce" (GAIL's cross-entropy).
    loss: str = "lsgan"
    # Gradient penalty weight w_gp of (w_gp/2)·E‖∇_φ D‖² (AMP Eq. 8, Table 4: 10; ControlVAE's w_g = 20
    # has no ½, i.e. w_gp = 40 here).
    w_gp: float = 10.0
    # What φ the penalty's gradient is taken against: "raw", the features Φ(s), Φ(s') as AMP's Eq. 8 writes
    # them, or "normalised", the normaliser's output, which weighs each raw gradient component by its
    # feature's variance (1e-4 to 10 on the walk), so its w_gp is not AMP's.
    gp_features: str = "normalised"
    # Where the penalty applies: "data" (AMP Eq. 8) or "data_and_policy" (the two penalties summed, as in
    # some public implementations).
    gp_on: str = "data"
    # Weight of w·‖W‖² on the logit layer's weights; 0 turns it off (AMP does not use it).
    logit_reg: float = 0.0
    # (L2) weight decay on every parameter; 0 turns it off.
    weight_decay: float = 0.0
    # Optimiser, "adam" or "sgd" (with `momentum`), and its step size. AMP's Table 4 is SGD, momentum 0.9,
    # 1e-5 (scale=paper); Adam at 1e-4 learns the walk/run separation of tests/learning in a few hundred
    # steps and is the default at the smaller scales.
    optimizer: str = "adam"
    momentum: float = 0.9
    lr: float = 1e-4
    # Transitions per side in one update (AMP Table 4: K = 256). The caller draws data and fresh policy
    # minibatches of this size; `update` takes whatever it is given.
    batch_size: int = 256
    # Global gradient-norm clip; None for no clipping (AMP does not clip).
    grad_clip: float | None = None
    # Past policy transitions kept for replay (AMP Table 4: B = 1e5).
    replay_capacity: int = 100_000
    # Fraction of each update's policy side drawn from the replay of past updates (the rest from the fresh
    # batch). 0 uses the fresh batch only; with an empty replay the fresh batch is used whatever this is.
    replay_mix: float = 0.5

    def __post_init__(self) -> None:
        check_loss_type(self.loss)
        if self.gp_on not in GP_ON:
            raise ValueError(f"unknown gradient penalty placement gp_on={self.gp_on!r}; expected one of {GP_ON}")
        if not 0.0 <= self.replay_mix <= 1.0:
            raise ValueError(f"replay_mix must lie in [0, 1], got {self.replay_mix}")
        if self.replay_capacity < 1 or self.batch_size < 1:
            raise ValueError("replay_capacity and batch_size must be at least 1")
        if self.w_gp < 0 or self.logit_reg < 0:
            raise ValueError("w_gp and logit_reg must be non-negative")
        if self.gp_features not in GP_FEATURES:
            raise ValueError(f"gp_features: unknown {self.gp_features!r}; expected one of {GP_FEATURES}")
        if self.optimizer not in DISC_OPTIMIZERS:
            raise ValueError(f"optimizer: unknown {self.optimizer!r}; expected one of {DISC_OPTIMIZERS}")
        if not 0.0 <= self.momentum < 1.0 or self.lr <= 0:
            raise ValueError("momentum must lie in [0, 1) and lr be positive")


@dataclass
class DiscriminatorBatch:
    """Transitions (Φ(s), Φ(s')) concatenated; NumPy arrays or tensors."""

    data_obs: Any  # [B, 2·obs_dim] from the reference motions
    policy_obs: Any  # [B', 2·obs_dim] from the policy's rollouts
    data_skill: Any = None  # [B] int skill labels, when the discriminator is skill-conditioned
    policy_skill: Any = None  # [B'] int skill labels, when the discriminator is skill-conditioned


class TransitionReplay:
    """A ring buffer of past policy transitions [capacity, dim] and, optionally, their skill labels."""

    def __init__(self, capacity: int, dim: int, with_skill: bool):
        self.capacity = capacity
        self.obs = np.empty((capacity, dim), dtype=np.float32)
        self.skill = np.empty(capacity, dtype=np.int64) if with_skill else None
        self.size = 0
        self._next = 0

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, skill: np.ndarray | None = None) -> None:
        obs = obs[-self.capacity :]
        idx = (self._next + np.arange(len(obs))) % self.capacity
        self.obs[idx] = obs
        if self.skill is not None:
            self.skill[idx] = skill[-self.capacity :]
        self._next = (self._next + len(obs)) % self.capacity
        self.size = min(self.size + len(obs), self.capacity)

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
        """n transitions drawn uniformly with replacement; the replay must not be empty."""
        idx = rng.integers(0, self.size, size=n)
        return self.obs[idx], None if self.skill is None else self.skill[idx]


class DiscriminatorLearner(Learner):
    """Owns the discriminator, its optimiser and the replay of past policy transitions.

    obs_dim: size of Φ(s) for one state (`workers.body.features.amp_dim`); inputs are [B, 2·obs_dim].
    seed:    seeds the network's initial weights and the replay sampler.
    """

    name = "disc"
    double_backward = True  # the gradient penalty (AMP Eq. 8)

    def __init__(
        self,
        obs_dim: int,
        config: DiscriminatorConfig | None = None,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ):
        self.config = config = config or DiscriminatorConfig()
        with cpu_seeded(seed):
            module = Discriminator(
                obs_dim, config.hidden, config.activation, config.num_skills, config.skill_embed_dim
            ).to(device)
        options = {"momentum": config.momentum} if config.optimizer == "sgd" else {}
        optimizer = make_optimizer(
            config.optimizer,
            module.parameters(),
            config.lr,
            weight_decay=config.weight_decay,
            **options,
        )
        super().__init__(module, optimizer, config.grad_clip, device)
        self.replay = TransitionReplay(config.replay_capacity, 2 * obs_dim, config.num_skills > 0)
        self.rng = np.random.default_rng(seed)

    # The step ----------------------------------------------------------------
    def update(self, batch: DiscriminatorBatch) -> dict[str, float]:
        """One step on `batch`, whose policy side is first mixed with replayed transitions (then stored)."""
        metrics = super().update(self._mix_replay(batch))
        metrics["replay_size"] = float(len(self.replay))
        return metrics

    def before_update(self, batch: DiscriminatorBatch) -> None:
        data = self._obs(batch.data_obs)
        if all_finite([data, self._obs(batch.policy_obs)]):  # a non-finite batch leaves the statistics alone
            self.module.update_normalizer(data)

    def loss(self, batch: DiscriminatorBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """AMP Eq. 8 on the batch as given (no replay), with diagnostics.

        Terms: loss_data, loss_policy, gp (gp_data [+ gp_policy]), input_grad_norm_data
        [input_grad_norm_policy], d_data, d_policy (mean logits), accuracy_data (D > 0),
        accuracy_policy (D < 0), accuracy (their mean) [, logit_reg].
        """
        cfg = self.config
        data_skill, policy_skill = self._skills(batch)
        penalise_policy = cfg.gp_on == "data_and_policy"
        data_in, data_n = self._penalised_input(batch.data_obs, True)
        policy_in, policy_n = self._penalised_input(batch.policy_obs, penalise_policy)
        d_data = self.module.logits(data_n, data_skill)
        d_policy = self.module.logits(policy_n, policy_skill)

        total, terms = discriminator_loss(d_data, d_policy, cfg.loss)
        gp, gp_terms = gradient_penalty(d_data, data_in, cfg.w_gp)
        terms["gp_data"], terms["input_grad_norm_data"] = gp_terms["gp"], gp_terms["input_grad_norm"]
        if penalise_policy:
            gp_policy, gp_terms = gradient_penalty(d_policy, policy_in, cfg.w_gp)
            terms["gp_policy"], terms["input_grad_norm_policy"] = gp_terms["gp"], gp_terms["input_grad_norm"]
            gp = gp + gp_policy
        terms["gp"] = gp
        total = total + gp
        if cfg.logit_reg > 0:
            reg, reg_terms = logit_regularization(self.module.logit_layer.weight, cfg.logit_reg)
            total = total + reg
            terms.update(reg_terms)

        acc_data = (d_data > 0).float().mean()
        acc_policy = (d_policy < 0).float().mean()
        terms.update(
            d_data=d_data.mean(),
            d_policy=d_policy.mean(),
            accuracy_data=acc_data,
            accuracy_policy=acc_policy,
            accuracy=0.5 * (acc_data + acc_policy),
        )
        return total, terms

    def _penalised_input(self, obs: Any, penalised: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """(the input the penalty differentiates against, the normalised transitions D reads): with
        gp_features raw the raw Φ, normalised through the graph; else the normalised ones themselves."""
        raw = self._obs(obs)
        if self.config.gp_features == "raw":
            raw = raw.detach().requires_grad_(penalised)
            return raw, self.module.normalize(raw)
        normalised = self.module.normalize(raw).detach().requires_grad_(penalised)
        return normalised, normalised

    def evaluate(self, batch: DiscriminatorBatch) -> dict[str, float]:
        """The loss terms on `batch` (no replay, no step, no side effect), e.g. on held-out transitions."""
        self.module.eval()
        total, terms = self.loss(batch)
        metrics = {k: float(v.detach()) for k, v in terms.items()}
        metrics["loss"] = float(total.detach())
        return metrics

    # Using the discriminator -------------------------------------------------
    @torch.no_grad()
    def logits(self, obs: Any, skill: Any = None) -> np.ndarray:
        """D on raw transitions [N, 2·obs_dim] (skills [N] int) -> logits [N]."""
        self.module.eval()
        return self.module(self._obs(obs), self._skill(skill)).cpu().numpy()

    @torch.no_grad()
    def reward(self, obs: Any, skill: Any = None) -> np.ndarray:
        """The style reward r_S [N] of transitions [N, 2·obs_dim] (AMP Eq. 7 for lsgan)."""
        self.module.eval()
        d = self.module(self._obs(obs), self._skill(skill))
        return style_reward(d, self.config.loss)[0].cpu().numpy()

    # Helpers -----------------------------------------------------------------
    def _mix_replay(self, batch: DiscriminatorBatch) -> DiscriminatorBatch:
        """Replace a `replay_mix` share of the policy side by replayed transitions, then store the fresh ones.

        A batch holding a non-finite number is passed on untouched and not stored, so its
        update is skipped and the replay is not poisoned.
        """
        if self.config.num_skills > 0 and (batch.data_skill is None or batch.policy_skill is None):
            raise ValueError(f"{self.name}: a skill-conditioned discriminator needs data_skill and policy_skill")
        data, policy = self._obs(batch.data_obs), self._obs(batch.policy_obs)
        if not all_finite([data, policy]):
            return batch
        fresh = policy.cpu().numpy()
        fresh_skill = None if batch.policy_skill is None else self._skill(batch.policy_skill).cpu().numpy()
        n = len(fresh)
        n_replay = min(round(self.config.replay_mix * n), n) if len(self.replay) else 0
        obs, skill = fresh, fresh_skill
        if n_replay:
            keep = self.rng.permutation(n)[: n - n_replay]
            old, old_skill = self.replay.sample(n_replay, self.rng)
            obs = np.concatenate((fresh[keep], old))
            if fresh_skill is not None:
                skill = np.concatenate((fresh_skill[keep], old_skill))
        self.replay.add(fresh, fresh_skill)
        return DiscriminatorBatch(data, obs, batch.data_skill, skill)

    def _skills(self, batch: DiscriminatorBatch) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        return self._skill(batch.data_skill), self._skill(batch.policy_skill)

    def _obs(self, x: Any) -> torch.Tensor:
        return self.tensor(x)

    def _skill(self, x: Any) -> torch.Tensor | None:
        return None if x is None else torch.as_tensor(x, dtype=torch.long, device=self.device)


def reference_transitions(character: Character, library: MotionLibrary) -> np.ndarray:
    """Every consecutive pair of reference frames as (Φ(s), Φ(s')) [N, 2·amp_dim] (looping clips wrap)."""
    clips, frames = [], []
    for c, n in enumerate(library.num_frames):
        last = n if library.loop[c] else n - 1
        clips.append(np.full(last, c))
        frames.append(np.arange(last))
    clip, frame = np.concatenate(clips), np.concatenate(frames)
    before = amp_features(character, library.state(clip, frame))
    after = amp_features(character, library.state(clip, frame + 1))
    return np.concatenate((before, after), axis=1)


def policy_transitions(tr: Trajectory) -> np.ndarray:
    """(Φ(s), Φ(s')) [T·M, 2·amp_dim] of a trajectory, time-major (the rollout worker records Φ: `AMPFeatures`)."""
    before, after = tr.extras["amp_obs"], tr.extras["amp_next_obs"]
    return np.concatenate((before, after), axis=-1).reshape(-1, 2 * before.shape[-1])


def amp_reward(
    style: np.ndarray, task: np.ndarray | None, task_weight: float, style_weight: float
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """AMP Eq. 4, r = w_G·r_G + w_S·r_S, of style rewards [T, M] and task rewards (None: none, 0); (r as float32,
    its named terms {"style", "task", "total"})."""
    task = np.zeros_like(style) if task is None else task
    total = (task_weight * task + style_weight * style).astype(np.float32)
    return total, {"style": style, "task": task, "total": total}
