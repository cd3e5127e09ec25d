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

from orchestrator.algos.onpolicy import OnPolicy
from workers.recorders import ImitationReward


class Tracker(OnPolicy):
    sections = ("ppo", "imitation")
    observation = "imitation"
    residual = True

    @classmethod
    def observation_of(cls, cfg) -> str:
        return cfg.algo.imitation.observation

    @classmethod
    def make_recorders(cls, cfg, character) -> list[ImitationReward]:
        return [ImitationReward(character, dict(cfg.algo.imitation.weights))]
