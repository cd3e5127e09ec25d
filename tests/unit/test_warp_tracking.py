"""PD tracking of every bundled clip with the root welded 2 m up (no contacts: no chaos), on MuJoCo Warp (Warp's CPU
device, or MOCAP_WARP_DEVICE) against MuJoCo C: the same per-joint errors, clip by clip.

Each clip is one world; every control step sets the PD targets to the reference's next pose and advances 16
physics steps at 480 Hz, for 60 control steps (2 s) from the clip's first frame. The error of a joint is the angle
between its pose and the target (degrees; ball joints' rotation angle, hinges' difference), as
tests/unit/test_character.py measures the servo's lag. Compiles MuJoCo Warp's kernels on a cold cache: `slow`.

Measured on Warp's CPU device (20 clips, mean joint error 6.35 deg on MuJoCo C): each clip's mean error within
2.2e-5 deg of MuJoCo C's, every joint at every step within 5.6e-3 deg. The bounds (1e-2, 1e-1) catch one physics
step too many per control step (0.58 deg, 4.5 deg) and PD targets off by 0.001 rad (0.020 deg, 0.13 deg).
"""

from __future__ import annotations

import os

import mujoco
import numpy as np
import pytest

pytest.importorskip("mujoco_warp")

from workers.body import rotations as rot  # noqa: E402
from workers.body.character import Character  # noqa: E402
from workers.motion.formats import bundled_clip_names  # noqa: E402
from workers.motion.library import MotionLibrary  # noqa: E402
from workers.sim.warp_physics import WarpPhysics  # noqa: E402

DEVICE = os.environ.get("MOCAP_WARP_DEVICE", "cpu")
HZ, STEPS = 480.0, 60
K = int(HZ / 30)


def joint_errors(c: Character, qpos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[..., joints] degrees between poses (welded-root qpos) and targets."""
    ball = rot.angle(rot.mul(rot.conj(qpos[..., c.ball_qpos]), target[..., c.ball_qpos]))
    hinge = np.abs(qpos[..., c.hinge_qpos] - target[..., c.hinge_qpos])
    return np.degrees(np.concatenate((ball, hinge), axis=-1))


@pytest.mark.slow
def test_every_bundled_clip_tracks_with_the_same_errors_on_both_engines(character, clip_cache):
    names = bundled_clip_names()
    lib = MotionLibrary.load(character, names, fps=30, cache_dir=clip_cache)
    welded = Character.load(sim_hz=HZ, fixed_root=True, root_height=2.0)
    m = welded.model
    clips = np.arange(len(names))
    frames = [np.minimum(t, lib.num_frames - 1) for t in range(STEPS + 1)]
    refs = [lib.state(clips, f) for f in frames]
    warp = WarpPhysics(m, len(names), device=DEVICE)
    warp.set_state(clips, refs[0].qpos[:, 7:], refs[0].qvel[:, 6:])
    datas = []
    for i in clips:
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = refs[0].qpos[i, 7:], refs[0].qvel[i, 6:]
        mujoco.mj_forward(m, d)
        datas.append(d)
    err_c, err_w = [], []
    for t in range(1, STEPS + 1):
        target = refs[t].qpos[:, 7:]
        ctrl = welded.qpos_to_action(target)
        warp.set_ctrl(ctrl)
        warp.step(K)
        for i, d in enumerate(datas):
            d.ctrl[:] = ctrl[i]
            mujoco.mj_step(m, d, nstep=K)
        err_c.append(joint_errors(welded, np.array([d.qpos for d in datas]), target))
        err_w.append(joint_errors(welded, warp.qpos.cpu().numpy().astype(np.float64), target))
    err_c, err_w = np.array(err_c), np.array(err_w)  # [steps, clips, joints]
    assert np.isfinite(err_w).all() and err_c.mean() > 1.0  # the servos lag: there is an error to compare
    per_clip = np.abs(err_w.mean(axis=(0, 2)) - err_c.mean(axis=(0, 2)))
    worst = np.abs(err_w - err_c).max(axis=(0, 2))
    print(
        f"{len(names)} clips: mean joint error {err_c.mean():.3f} deg on MuJoCo C; Warp - C per clip: mean "
        f"{per_clip.max():.2e} deg at most, any joint and step {worst.max():.2e} deg at most"
    )
    assert per_clip.max() < 1e-2, dict(zip(names, per_clip.round(5), strict=True))
    assert worst.max() < 1e-1, dict(zip(names, worst.round(4), strict=True))
