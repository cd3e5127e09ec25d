"""The imitation reward of a tracking expert and the observation it acts on; ControlVAE's tracking reward (Eq. 20).

A DeepMimic-style imitation reward in the multiplicative form of Won et al. 2020
(whose imitation controllers PhysicsVAE distils): one exponential term per
error, multiplied, so that the reward is high only when every term is,

    r = Π_k exp(−w_k · e_k) = exp(−Σ_k w_k · e_k)

with the errors between the simulated state and the reference at the same time:

- pose:         Σ over the root and every joint of the squared rotation angle
                between simulated and reference local rotations (hinges: the
                angle difference), rad².
- velocity:     Σ over the actuated dofs of the squared joint-velocity error, (rad/s)².
- end_effector: Σ over hands and feet of the squared position error relative to
                the root, in the heading frame, m².
- root:         squared root-position error in the world, m².

The weights are DeepMimic's scales (pose 2, velocity 0.1, end-effector 40,
root/centre of mass 10). A weight of 0 drops its term. Every term is returned
by name so that each is logged (`reward/pose`, ...).

The tracker's observation is the simulated state s and the reference state one
control step ahead, s̃_{t+1} (what ControlVAE's posterior reads, and the
"future reference frames" of Won et al. reduced to one).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from workers.body.character import Character
from workers.body.features import heading_inverse
from workers.types import KinState

IMITATION_TERMS = ("pose", "velocity", "end_effector", "root")
DEFAULT_WEIGHTS = {"pose": 2.0, "velocity": 0.1, "end_effector": 40.0, "root": 10.0}


def _quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle [...] between unit quaternions a, b [..., 4] (w, x, y, z)."""
    dot = np.abs(np.sum(a * b, axis=-1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


def imitation_errors(character: Character, sim: KinState, ref: KinState) -> dict[str, np.ndarray]:
    """The squared errors e_k [N] of each term between simulated and reference states [N]."""
    balls = character.ball_qpos  # [n_ball, 4]
    pose = _quat_angle(sim.qpos[:, 3:7], ref.qpos[:, 3:7]) ** 2
    pose = pose + np.sum(_quat_angle(sim.qpos[:, balls], ref.qpos[:, balls]) ** 2, axis=-1)
    hinges = character.hinge_qpos
    pose = pose + np.sum((sim.qpos[:, hinges] - ref.qpos[:, hinges]) ** 2, axis=-1)
    dof0 = character.root_dofs
    velocity = np.sum((sim.qvel[:, dof0:] - ref.qvel[:, dof0:]) ** 2, axis=-1)
    ee = character.end_effectors

    def ee_local(s: KinState) -> np.ndarray:
        rel = s.xpos[:, ee] - s.xpos[:, :1]
        return rel @ heading_inverse(s.xquat[:, 0]).transpose(0, 2, 1)

    end_effector = np.sum((ee_local(sim) - ee_local(ref)) ** 2, axis=(-1, -2))
    root = np.sum((sim.xpos[:, 0] - ref.xpos[:, 0]) ** 2, axis=-1)
    return {"pose": pose, "velocity": velocity, "end_effector": end_effector, "root": root}


def check_weights(weights: Mapping[str, float]) -> None:
    """Refuse a weight for a term the imitation reward does not have."""
    unknown = set(weights) - set(IMITATION_TERMS)
    if unknown:
        raise ValueError(f"unknown imitation reward terms {sorted(unknown)}; expected {IMITATION_TERMS}")


def imitation_reward(
    character: Character, sim: KinState, ref: KinState, weights: Mapping[str, float] = DEFAULT_WEIGHTS
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(r [N] in (0, 1], {term: exp(−w_k e_k) [N]}) for simulated and reference states [N]."""
    check_weights(weights)
    errors = imitation_errors(character, sim, ref)
    terms = {k: np.exp(-float(weights.get(k, 0.0)) * errors[k]) for k in IMITATION_TERMS}
    total = np.prod(np.stack(list(terms.values())), axis=0)
    return total.astype(np.float32), {k: v.astype(np.float32) for k, v in terms.items()}


def imitation_observation(state: np.ndarray, ref_next: np.ndarray) -> np.ndarray:
    """The tracker's observation [N, 2D]: s [N, D] and the reference's next s̃_{t+1} [N, D]."""
    return np.concatenate((state, ref_next), axis=-1).astype(np.float32)


def tracking_reward(state: np.ndarray, ref_state: np.ndarray, weights: np.ndarray, temperature: float = 20.0):
    """ControlVAE's Eq. 20, the reward data balancing reads (`workers.replay.balancing`): exp(−‖W(s̃ − s)‖₁ / T_V)
    over the last axis of s [..., D], W a weight per feature [D]."""
    return np.exp(-np.abs((ref_state - state) * weights).sum(-1) / temperature).astype(np.float32)
