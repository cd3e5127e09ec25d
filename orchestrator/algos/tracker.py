"""A tracking expert by PPO: DeepMimic-style imitation of the reference clips.

The reward is the multiplicative imitation reward of Won et al. 2020 (`workers.rewards`:
pose, velocity, end-effector and root terms), recorded by the rollout workers from the
simulated and reference states; the policy observes s and the reference's next s̃_{t+1}
(or, with `algo.imitation.observation=mimic`, PULSE's s_g-mimic: the reference's next
state as offsets from the character) and acts as an offset from the reference's next
pose (so that the untrained policy is PD tracking of the clip, which earns some reward;
absolute targets near the zero pose earn none under this product). Reference state
initialisation, early termination on a fall and on a tracking failure (head 0.5 m off
for 1 s). The same worker, learner and loop as AMP, with the reward from the environment
instead of a discriminator. Its output, the expert policy, is what PhysicsVAE and PULSE
distil.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from orchestrator.algos.onpolicy import OnPolicy, PPOAlgo
from orchestrator.schema import ConfigError
from workers.recorders import ImitationReward
from workers.rewards import DEFAULT_WEIGHTS as IMITATION_WEIGHTS
from workers.rewards import IMITATION_TERMS


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
class TrackerAlgo(PPOAlgo):
    imitation: ImitationConfig = field(default_factory=ImitationConfig)


class Tracker(OnPolicy):
    config_class = TrackerAlgo
    observation = "imitation"
    residual = True

    @classmethod
    def observation_of(cls, cfg) -> str:
        return cfg.algo.imitation.observation

    @classmethod
    def make_recorders(cls, cfg, character) -> list[ImitationReward]:
        return [ImitationReward(character, dict(cfg.algo.imitation.weights))]
