"""Evaluation videos: the rollouts to show, recorded as qpos per control step, and their offscreen rendering.

Recording (simulation, no GL):
- `record_fall_rollouts`: time-until-fall rollouts as `workers.evaluation.controller.time_until_fall` runs them
  (the fixed start, the walk clip's frame 0, z from the prior every control step), each cut one second after its
  first fall.
- `record_tracking`: one clip tracked with the posterior, as `workers.evaluation.controller.tracking_error` does,
  with the reference's qpos beside it (drawn as a ghost).
- `record_policy_episode`: one episode of an actor (a PPO policy's mean action) from a reference start,
  with its reference, until it falls or the clip ends.

Rendering (`render_frames`) needs an OpenGL context, which MuJoCo chooses from MUJOCO_GL when it is
first imported; `orchestrator.video` therefore renders in a child process with MUJOCO_GL set. The
camera follows the character's root at a fixed angle (a side view), and a reference is drawn as a
translucent copy of the character's geoms (`mjv_addGeoms` of a second MjData, no physics, so it
collides with nothing) offset `GHOST_OFFSET_M` to the camera's right.

The recording functions import torch and the evaluation code only when called, so that the render
process loads neither.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

import mujoco
import numpy as np

if TYPE_CHECKING:
    from workers.body.character import Character
    from workers.models.vae import VAEController
    from workers.motion.library import MotionLibrary
    from workers.sim.env import SimConfig, Simulator, StepResult

# The camera: distance (m), azimuth and elevation (degrees; azimuth 90 looks along +y, a side view of
# the clips, which walk along x), and the height (m) it looks at, fixed so that a fall stays in frame.
CAMERA_DISTANCE_M = 3.6
CAMERA_AZIMUTH_DEG = 100.0
CAMERA_ELEVATION_DEG = -12.0
CAMERA_HEIGHT_M = 0.8
HEADLIGHT_AMBIENT, HEADLIGHT_DIFFUSE = 0.3, 0.6
# The ghost (the reference): how far beside the character, and its colour (translucent blue).
GHOST_OFFSET_M = 1.0
GHOST_RGBA = (0.35, 0.6, 1.0, 0.3)
# How long a time-until-fall video goes on after the fall.
FALL_TAIL_S = 1.0


@dataclasses.dataclass
class Recording:
    """One video's worth of poses: qpos [T, nq] per frame, the reference's (the ghost) or None, and the
    model they are poses of (the simulator's: the character on its terrain)."""

    name: str
    qpos: np.ndarray
    ghost_qpos: np.ndarray | None = None
    model: mujoco.MjModel | None = None

    @property
    def frames(self) -> int:
        return len(self.qpos)


# ----------------------------------------------------------------------------
# Recording
# ----------------------------------------------------------------------------
def record_fall_rollouts(
    controller: VAEController,
    character: Character,
    library: MotionLibrary,
    num_rollouts: int,
    max_seconds: float,
    sim_config: SimConfig | None = None,
    seed: int = 0,
) -> list[Recording]:
    """`num_rollouts` time-until-fall rollouts ("fall-<i>"), with `time_until_fall`'s start and sampling.

    Each has the start pose and then one pose per control step, up to `max_seconds`, ending
    `FALL_TAIL_S` after its first fall.
    """
    import torch

    from workers.evaluation.controller import fall_start, prior_action
    from workers.models.nets import evaluation_mode
    from workers.sim.env import make_sim, without_tracking_termination
    from workers.sim.episodes import run_episodes

    if num_rollouts < 1:
        return []
    config = without_tracking_termination(sim_config)
    clip, frame = fall_start(library)
    sim = make_sim(character, library, num_rollouts, config, seed=seed)
    sim.reset(np.arange(num_rollouts), np.full(num_rollouts, clip), np.full(num_rollouts, frame))
    generator = torch.Generator().manual_seed(seed)
    steps = max(1, int(round(max_seconds * config.control_hz)))
    tail = int(round(FALL_TAIL_S * config.control_hz))
    qpos = [sim.kin_state().qpos]
    end = np.full(num_rollouts, steps)  # the last step shown

    def after(t: int, result: StepResult) -> bool:
        qpos.append(result.kin.qpos)
        end[:] = np.where(result.fell & (end == steps), np.minimum(t + tail, steps), end)
        return bool((t >= end).all())

    with evaluation_mode(controller):
        run_episodes(sim, lambda sim, _: prior_action(controller, sim, generator), steps, after, states=False)
    poses = np.stack(qpos, axis=1)  # [R, T, nq]
    return [Recording(f"fall-{r}", poses[r, : end[r] + 1], model=sim.model) for r in range(num_rollouts)]


def record_tracking(
    controller: VAEController,
    character: Character,
    library: MotionLibrary,
    max_seconds: float,
    sim_config: SimConfig | None = None,
    seed: int = 0,
    clip: str | None = None,
) -> Recording:
    """One clip (`clip`, else `fall_start`'s) tracked from its first frame with the posterior mean, as
    `tracking_error` tracks a segment, for up to `max_seconds` (a one-shot clip: until its last frame)."""
    from workers.evaluation.controller import fall_start, posterior_mean_action
    from workers.models.nets import evaluation_mode
    from workers.sim.env import make_sim, without_tracking_termination
    from workers.sim.episodes import run_episodes

    config = without_tracking_termination(sim_config)
    c = library.clip_id(clip) if clip is not None else fall_start(library)[0]
    steps = _steps(library, c, max_seconds, config.control_hz)
    sim = make_sim(character, library, 1, config, seed=seed)
    sim.reset(np.zeros(1, int), np.array([c]), np.zeros(1, int))
    qpos, ref = [sim.kin_state().qpos[0]], [sim.reference_state().qpos[0]]

    def after(t: int, result: StepResult) -> None:
        qpos.append(result.kin.qpos[0])
        ref.append(sim.reference_state().qpos[0])

    with evaluation_mode(controller):
        run_episodes(sim, lambda sim, _: posterior_mean_action(controller, sim), steps, after, states=False)
    return Recording(f"tracking-{_slug(library.names[c])}", np.stack(qpos), np.stack(ref), sim.model)


def record_policy_episode(
    act: Callable[[Simulator, np.ndarray], np.ndarray],
    character: Character,
    library: MotionLibrary,
    max_seconds: float,
    sim_config: SimConfig | None = None,
    seed: int = 0,
) -> Recording:
    """One episode of `act` (sim, body states -> actions, as `pose_error_episodes` takes it) from a reference
    start drawn by the simulator, with its reference, until `max_seconds`, `FALL_TAIL_S` after a fall or the
    clip's end."""
    from workers.sim.env import make_sim, without_tracking_termination
    from workers.sim.episodes import run_episodes

    config = without_tracking_termination(sim_config)
    sim = make_sim(character, library, 1, config, seed=seed)
    steps = max(1, int(round(max_seconds * config.control_hz)))
    tail = int(round(FALL_TAIL_S * config.control_hz))
    qpos, ref = [sim.kin_state().qpos[0]], [sim.reference_state().qpos[0]]
    end = [steps]

    def after(t: int, result: StepResult) -> bool:
        qpos.append(result.kin.qpos[0])
        ref.append(sim.reference_state().qpos[0])
        if result.clip_ended[0]:
            return True
        if result.fell[0] and end[0] == steps:
            end[0] = min(t + tail, steps)
        return t >= end[0]

    run_episodes(sim, act, steps, after)
    return Recording(f"policy-{_slug(library.names[int(sim.clip_id[0])])}", np.stack(qpos), np.stack(ref), sim.model)


def _steps(library: MotionLibrary, clip: int, seconds: float, control_hz: float) -> int:
    steps = max(1, int(round(seconds * control_hz)))
    if not library.loop[clip]:
        steps = min(steps, max(int(library.num_frames[clip]) - 1, 1))
    return steps


def _slug(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


# ----------------------------------------------------------------------------
# Rendering (needs an OpenGL context: MUJOCO_GL=egl or osmesa without a display)
# ----------------------------------------------------------------------------
def camera_right(azimuth_deg: float = CAMERA_AZIMUTH_DEG) -> np.ndarray:
    """The horizontal unit vector pointing to the right of the image, for a camera at this azimuth."""
    a = np.deg2rad(azimuth_deg)
    return np.array([np.sin(a), -np.cos(a), 0.0])


def render_frames(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    ghost_qpos: np.ndarray | None = None,
    width: int = 480,
    height: int = 320,
    shadows: bool = False,
    multisamples: int = 0,
) -> Iterator[np.ndarray]:
    """RGB frames [height, width, 3] uint8, one per row of qpos [T, nq], the camera on the character's root.

    With `ghost_qpos` [T, nq] a translucent copy of the character in that pose stands `GHOST_OFFSET_M` to
    the right in the image, and the camera looks between the two. Shadows and multisample anti-aliasing
    are off by default: without a GPU (Mesa's llvmpipe) MuJoCo's shadow map makes a frame 4-5 times
    slower, and 4x multisampling (the model's default) 2-3 times.
    """
    qpos = np.asarray(qpos, dtype=np.float64)
    if ghost_qpos is not None and np.shape(ghost_qpos) != qpos.shape:
        raise ValueError(f"ghost_qpos {np.shape(ghost_qpos)} must match qpos {qpos.shape}")
    model = copy.copy(model)  # the offscreen buffer must hold the frame; the caller's model is left as it was
    model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
    model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
    model.vis.quality.offsamples = multisamples
    model.vis.headlight.ambient[:] = HEADLIGHT_AMBIENT  # without shadows, a brighter headlight reads better
    model.vis.headlight.diffuse[:] = HEADLIGHT_DIFFUSE
    data, ghost = mujoco.MjData(model), mujoco.MjData(model)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.azimuth, camera.elevation = CAMERA_AZIMUTH_DEG, CAMERA_ELEVATION_DEG
    camera.distance = CAMERA_DISTANCE_M + (0.5 * GHOST_OFFSET_M if ghost_qpos is not None else 0.0)
    offset = GHOST_OFFSET_M * camera_right()
    option, perturb = mujoco.MjvOption(), mujoco.MjvPerturb()
    renderer = mujoco.Renderer(model, height=height, width=width)
    try:
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadows
        for t in range(len(qpos)):
            data.qpos[:] = qpos[t]
            mujoco.mj_kinematics(model, data)
            lookat = data.xpos[1].copy()  # the root body
            if ghost_qpos is not None:
                ghost.qpos[:] = ghost_qpos[t]
                mujoco.mj_kinematics(model, ghost)
                lookat = 0.5 * (lookat + ghost.xpos[1] + offset)
            camera.lookat[:] = (lookat[0], lookat[1], CAMERA_HEIGHT_M)
            renderer.update_scene(data, camera, option)
            if ghost_qpos is not None:
                scene = renderer.scene
                first = scene.ngeom
                mujoco.mjv_addGeoms(model, ghost, option, perturb, mujoco.mjtCatBit.mjCAT_DYNAMIC, scene)
                for g in range(first, scene.ngeom):
                    scene.geoms[g].rgba[:] = GHOST_RGBA
                    scene.geoms[g].pos[:] += offset
            yield renderer.render()
    finally:
        renderer.close()
