"""AMP's evaluation of an imitation policy: pose error after dynamic time warping (Peng et al. 2021, Table 3).

`pose_error_episodes` runs `num_episodes` episodes as the environments of one
`Simulator`, each from a reference state drawn from the library (reference state
initialisation, as in training), with the policy's deterministic action, for up
to `max_seconds` or until the character falls (or a one-shot clip ends). Each
episode's simulated poses are compared with the reference clip over the same
steps, after aligning the two sequences by dynamic time warping with Eq. 10 as
the cost (`workers.evaluation.pose_error`): positions of every body relative to the root,
in each frame's heading frame (so a character that walks the clip's gait but
drifts in heading is judged by its pose), mean over bodies, metres.

That heading frame and the mean over the B − 1 non-root bodies are ours. Eq. 10 as AMP
writes it takes the offsets from the root on the world axes and divides by N_joint, every
joint of the body, the root's own zero term included; it is reported beside ours as
"dtw_eq10" (DTW under its own cost). The plain per-frame error (no warping) is reported too:
a policy that imitates the gait at a slightly different pace has a small DTW error and a
growing per-frame error.
"""

from __future__ import annotations

import numpy as np

from workers.body.character import Character
from workers.body.features import heading_inverse
from workers.evaluation.pose_error import dtw_pose_error, eq10_dtw_pose_error, per_frame_pose_error, relative_positions
from workers.motion.library import MotionLibrary
from workers.sim.env import SimConfig, Simulator, StepResult, make_sim, without_tracking_termination
from workers.sim.episodes import Actor, run_episodes
from workers.types import KinState


def _relative(kin: KinState) -> np.ndarray:
    """Root-relative body positions [N, B-1, 3] in each character's heading frame."""
    return relative_positions(kin.xpos, heading_inverse=heading_inverse(kin.xquat[:, 0]))


def pose_error_episodes(
    act: Actor,
    character: Character,
    library: MotionLibrary,
    num_episodes: int = 32,
    max_seconds: float = 20.0,
    sim_config: SimConfig | None = None,
    seed: int = 0,
) -> dict:
    """Per-episode DTW pose error, per-frame error and length; their means; the error over time.

    Returns {"dtw": mean over episodes (m), "dtw_eq10": the same by Eq. 10 as written (m), "per_frame":
    mean (m), "seconds": mean episode length (s), "episodes": [{"dtw", "dtw_eq10", "per_frame", "seconds"}...],
    "curve_t": [K] seconds, "curve": [K] mean DTW cost at that time over the episodes still running}.
    """

    config = without_tracking_termination(sim_config)
    sim = make_sim(character, library, num_episodes, config, seed=seed)
    steps = max(1, int(round(max_seconds * config.control_hz)))
    start_clip, start_frame = sim.clip_id.copy(), sim.start_frame.copy()
    sim_pos = np.zeros((steps, num_episodes, character.num_bodies - 1, 3))
    sim_xpos = np.zeros((steps, num_episodes, character.num_bodies, 3))  # for Eq. 10 as written
    alive = np.ones(num_episodes, bool)
    length = np.zeros(num_episodes, int)

    def after(t: int, result: StepResult) -> bool:
        sim_pos[t - 1] = _relative(result.kin)
        sim_xpos[t - 1] = result.kin.xpos
        length[alive] += 1
        alive[:] &= ~(result.fell | result.clip_ended)
        return not alive.any()

    run_episodes(sim, act, steps, after)
    episodes, curves = [], []
    for e in range(num_episodes):
        n = int(length[e])
        frames = start_frame[e] + 1 + np.arange(n)
        ref_kin = library.state(np.full(n, start_clip[e]), frames)
        ref = _relative(ref_kin)
        warped = dtw_pose_error(sim_pos[:n, e], ref)
        eq10 = eq10_dtw_pose_error(sim_xpos[:n, e], ref_kin.xpos)
        episodes.append(
            {
                "dtw": float(warped["error"]),
                "dtw_eq10": float(eq10),
                "per_frame": float(per_frame_pose_error(sim_pos[:n, e], ref).mean()),
                "seconds": n / config.control_hz,
                "clip": library.names[start_clip[e]],
                "start_frame": int(start_frame[e]),
            }
        )
        # The cost at each simulated step: the mean over the path's cells on that step.
        cost = np.bincount(warped["index_a"], weights=warped["per_step"], minlength=n)
        count = np.bincount(warped["index_a"], minlength=n)
        curves.append(cost / np.maximum(count, 1))
    longest = max(len(c) for c in curves)
    total, count = np.zeros(longest), np.zeros(longest)
    for c in curves:
        total[: len(c)] += c
        count[: len(c)] += 1
    return {
        "dtw": float(np.mean([e["dtw"] for e in episodes])),
        "dtw_eq10": float(np.mean([e["dtw_eq10"] for e in episodes])),
        "per_frame": float(np.mean([e["per_frame"] for e in episodes])),
        "seconds": float(np.mean([e["seconds"] for e in episodes])),
        "episodes": episodes,
        "curve_t": ((np.arange(longest) + 1) / config.control_hz).tolist(),
        "curve": (total / np.maximum(count, 1)).tolist(),
    }


def reference_actor(library: MotionLibrary) -> Actor:
    """PD targets of the reference's next frame: a baseline 'policy' that needs no learning."""

    def act(sim: Simulator, bs: np.ndarray) -> np.ndarray:
        ref = library.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        return sim.character.qpos_to_action(ref.qpos)

    return act
