"""Warp kernels of our own that run beside MuJoCo Warp's in `workers.sim.warp_physics.WarpPhysics`.

Imported by `WarpPhysics` when one is made (this module imports warp, which the rest of workers/ runs
without).

`reset_unstable` is MuJoCo C's instability check, which MuJoCo Warp does not have. MuJoCo C checks
every physics step: `mj_checkPos` and `mj_checkVel` at the start of the position stage (`mj_step1`,
`mj_forward`) and `mj_checkAcc` once the accelerations are known, before integrating. A world with a
non-finite or huge (> mjMAXVAL) value is reset with `mj_resetData` (the model's qpos0 at rest, zero
controls, activations, warm start and time, and its warning counters cleared) and the warning is then
counted, so a world's count of each of the three is 1 after such a reset and 0 for the others. The
kernel does the same per world, between MuJoCo Warp's physics steps, on the device and without a copy
to the host; `WarpPhysics` launches it (and captures it in its graphs) where MuJoCo C checks.
"""

import mujoco
import warp as wp

MAXVAL = wp.constant(float(mujoco.mjMAXVAL))
# Columns of the counters, in the order MuJoCo C meets the checks within a physics step that the kernel
# follows: the accelerations of the step just taken, then the new positions and velocities.
QACC, QPOS, QVEL = 0, 1, 2
FIELDS = ("qacc", "qpos", "qvel")  # the counters' columns by name


@wp.func
def _bad(x: float) -> bool:
    return not wp.isfinite(x) or wp.abs(x) > MAXVAL


@wp.func
def _row_bad(a: wp.array2d(dtype=float), w: int) -> bool:
    for i in range(a.shape[1]):
        if _bad(a[w, i]):
            return True
    return False


@wp.kernel
def reset_unstable(
    check_acc: int,
    qpos0: wp.array(dtype=float),
    qpos: wp.array2d(dtype=float),
    qvel: wp.array2d(dtype=float),
    qacc: wp.array2d(dtype=float),
    ctrl: wp.array2d(dtype=float),
    act: wp.array2d(dtype=float),
    warmstart: wp.array2d(dtype=float),
    time: wp.array(dtype=float),
    counts: wp.array2d(dtype=int),
):
    """World w: if its qacc (when `check_acc`), qpos or qvel holds a non-finite or huge value, reset it as
    mj_resetData does and set its counters to 1 for the first check that failed, 0 for the others."""
    w = wp.tid()
    which = int(-1)  # noqa: UP018 (a dynamic variable in Warp, which a bare literal is not)
    if check_acc != 0 and _row_bad(qacc, w):
        which = QACC
    elif _row_bad(qpos, w):
        which = QPOS
    elif _row_bad(qvel, w):
        which = QVEL
    if which < 0:
        return
    for i in range(qpos.shape[1]):
        qpos[w, i] = qpos0[i]
    for i in range(qvel.shape[1]):
        qvel[w, i] = 0.0
        qacc[w, i] = 0.0
        warmstart[w, i] = 0.0
    for i in range(ctrl.shape[1]):
        ctrl[w, i] = 0.0
    for i in range(act.shape[1]):
        act[w, i] = 0.0
    time[w] = 0.0
    for k in range(3):
        counts[w, k] = 0
    counts[w, which] = 1
