"""The config sections of the methods that have no learner config of their own (`orchestrator.schema.SECTIONS`
holds every section, the learners' dataclasses among them): AMP's reward mix, the tracking expert's imitation
reward, PhysicsVAE's demos and offline training, PULSE's prior-action switch. Each field is documented where it
is declared.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from orchestrator.errors import ConfigError
from workers.rewards import DEFAULT_WEIGHTS as IMITATION_WEIGHTS
from workers.rewards import IMITATION_TERMS


@dataclass
class AMPConfig:
    # AMP's reward r = w_G·r_G + w_S·r_S (Eq. 4). Single-clip imitation (Sec. 8.4) trains on the style
    # reward alone: w_G = 0, w_S = 1. With a task, AMP uses w_G = w_S = 0.5.
    task_weight: float = 0.0
    style_weight: float = 1.0

    def __post_init__(self) -> None:
        for key in ("task_weight", "style_weight"):
            if getattr(self, key) < 0:
                raise ConfigError(f"algo.amp.{key} must be non-negative, got {getattr(self, key)}")


@dataclass
class ImitationConfig:
    # Weights w_k of the tracking expert's multiplicative reward exp(−Σ w_k e_k) (workers/rewards.py):
    # DeepMimic's scales. 0 drops a term.
    weights: dict[str, float] = field(default_factory=lambda: dict(IMITATION_WEIGHTS))

    # What the expert observes beside s (workers/policies.py): "imitation", the reference's next state in its
    # own heading frame (blind to drift from the clip); "mimic", PULSE's s_g-mimic (§4.1), the reference's next
    # state as offsets from the character in the character's heading frame (workers/models/tracking_goal.py).
    observation: str = "imitation"

    def __post_init__(self) -> None:
        if self.observation not in ("imitation", "mimic"):
            raise ConfigError(f"algo.imitation.observation: expected 'imitation' or 'mimic', got {self.observation!r}")
        for key, w in self.weights.items():
            if key not in IMITATION_TERMS:
                raise ConfigError(f"algo.imitation.weights.{key}: unknown term; expected one of {IMITATION_TERMS}")
            if w < 0:
                raise ConfigError(f"algo.imitation.weights.{key} must be non-negative, got {w}")


@dataclass
class DemosConfig:
    # Expert rollouts per clip of the motion config, from its frame 0 (PhysicsVAE Sec. 5.1.1: 10).
    rollouts_per_clip: int = 10
    # Gaussian noise added to the expert's (mean) action, std in radians of PD target (PhysicsVAE: 0.05).
    noise: float = 0.05
    # Length of a rollout: a looping clip is tracked this long, a one-shot clip to its last frame; a
    # rollout also ends where the expert falls.
    seconds: float = 10.0
    # Whose rollouts: "per_clip", one imitation controller per clip as PhysicsVAE trains them (§5.1.1): each
    # clip of motion.clips gets its own `algo.needs.expert` stage, trained on that clip alone (mirror off), and
    # a mirrored clip is driven by its clip's expert mirrored (workers/body/mirror.py); "shared", the one
    # expert stage trained on every clip (ControlVAE-style multi-clip tracking).
    experts: str = "per_clip"

    def __post_init__(self) -> None:
        if self.experts not in ("per_clip", "shared"):
            raise ConfigError(f"algo.demos.experts: expected 'per_clip' or 'shared', got {self.experts!r}")
        if self.rollouts_per_clip < 1:
            raise ConfigError(f"algo.demos.rollouts_per_clip must be at least 1, got {self.rollouts_per_clip}")
        if self.noise < 0:
            raise ConfigError(f"algo.demos.noise must be non-negative, got {self.noise}")
        if self.seconds <= 0:
            raise ConfigError(f"algo.demos.seconds must be positive, got {self.seconds}")


@dataclass
class OfflineConfig:
    # Offline training on a demos dataset (the world_model and physicsvae stages): one iteration is one
    # epoch, a pass over the training transitions. PhysicsVAE: the learning rate decays x0.7 every 50 epochs.
    lr_decay: float = 0.7
    decay_every: int = 50
    # Rollouts of each clip held out of training (the last ones) for the held-out metrics.
    holdout_rollouts: int = 1
    # The updates' arithmetic: "float32", or "bfloat16" (torch.autocast: the matmuls in bfloat16, the weights,
    # the optimiser and the losses' sums in float32; 1.6x an update on a CPU with bfloat16 GEMMs). It changes the
    # numbers, so it is part of the stage's hash, and it ships only where a paired study shows that it does not
    # change what the stages learn (docs/physicsvae.md).
    precision: str = "float32"

    def __post_init__(self) -> None:
        if self.precision not in ("float32", "bfloat16"):
            raise ConfigError(f"algo.offline.precision: expected 'float32' or 'bfloat16', got {self.precision!r}")
        if not 0 < self.lr_decay <= 1:
            raise ConfigError(f"algo.offline.lr_decay must be in (0, 1], got {self.lr_decay}")
        if self.decay_every < 1 or self.holdout_rollouts < 0:
            raise ConfigError("algo.offline.decay_every must be at least 1 and holdout_rollouts non-negative")


@dataclass
class PulseConfig:
    # PULSE's "prior-action" switch (Table 3): a downstream task policy acts as a residual on the learned
    # prior's mean, a = D(s, μ_task + μ_p) (Eq. 4). It changes nothing in the distillation itself; it is
    # part of the stage's config so that a task stage on this decoder reads it. Needs the learned prior.
    prior_action: bool = True
