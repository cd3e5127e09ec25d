"""What PULSE's online distillation needs from a tracking expert (Luo et al. 2024, Sec. 4.2).

`teacher_actions`: the expert labels arbitrary states (the student's own, as
DAgger-style online distillation visits them) with its deterministic action,
from stored (body states, clip, frame) arrays in one batch, outside any
simulator. How well a student then tracks is PULSE's success rule,
`workers.evaluation.success`.
"""

from __future__ import annotations

import numpy as np
import torch

from workers.body.character import Character
from workers.models import body_state
from workers.models.actor_critic import ActorCritic
from workers.models.nets import evaluation_mode
from workers.models.tracking_goal import mimic_goal
from workers.motion.library import MotionLibrary
from workers.rewards import imitation_observation


def teacher_actions(
    module: ActorCritic,
    character: Character,
    library: MotionLibrary,
    states: np.ndarray,
    clip_id: np.ndarray | int,
    frame: np.ndarray | int,
    residual: bool = True,
    observation: str = "imitation",
) -> np.ndarray:
    """The tracking expert's deterministic PD targets [N, A] (float32) for stored states.

    module: the expert, a PPO `ActorCritic` acting on `observation`: "imitation",
    (s, s̃_{t+1}) = (features(states), library.features(clip_id, frame + 1)), or "mimic",
    s and PULSE's s_g-mimic toward the reference's body states at frame + 1 (`workers.models.tracking_goal`).
    states: body states [N, B, 13] (`body_state.pack`); row i is at frame `frame[i]`
    of clip `clip_id[i]` (ints broadcast to all rows), i.e. `sim.start_frame + sim.steps`
    of the environment it came from. The action is the actor's mean μ(o) and, with
    `residual`, plus the PD targets that hold the reference's next pose,
    `character.qpos_to_action(library.state(clip_id, frame + 1).qpos)`: what
    `GaussianPolicy(module, "imitation", residual).mean_action` applies in a
    simulator, here for any rows at once. Eval mode, no gradients; the module's
    mode is restored after.
    """
    states = np.asarray(states, dtype=np.float32)
    if states.ndim != 3 or states.shape[-1] != body_state.BODY_STATE_SIZE:
        raise ValueError(f"states must be body states [N, B, {body_state.BODY_STATE_SIZE}], got {states.shape}")
    n = states.shape[0]
    clip_id = np.broadcast_to(np.asarray(clip_id, dtype=int), (n,))
    frame = np.broadcast_to(np.asarray(frame, dtype=int), (n,))
    with evaluation_mode(module):
        s = body_state.features_np(states)  # as the policy observes
        if observation == "imitation":
            obs = imitation_observation(s, library.features(clip_id, frame + 1))
        elif observation == "mimic":
            ref = body_state.pack(library.state(clip_id, frame + 1))
            goal = mimic_goal(torch.from_numpy(states), torch.from_numpy(ref)).numpy()
            obs = np.concatenate((s, goal), axis=-1)
        else:
            raise ValueError(f"a tracking expert observes 'imitation' or 'mimic', not {observation!r}")
        mean = module.mean(torch.from_numpy(obs)).numpy()
    if not residual:
        return mean
    base = library.pd_targets(clip_id, frame + 1)
    return mean + base
