"""How long MuJoCo Warp (workers.sim.warp_physics) and MuJoCo C agree from the same states.

    python scripts/warp_equivalence.py [--control-steps 300] [--device cpu] [--seed 0]

Six worlds of the humanoid at 480/30 Hz: four reference frames of the bundled walk and run clips
(feet on the floor), driven open loop by the references' PD targets, and two random perturbations of
the model's qpos0 (0.9 m up, random velocities) that hold their start pose's targets while they fall.
Each world is stepped by `WarpPhysics` (float32, on `--device`) and by `mujoco.mj_step` on its own
MjData (float64) under the same controls. Every 15 control steps it prints each world's largest
qpos and body-position difference, and at the end the first control step at which each world's body
positions differed by more than 1e-4, 1e-3 and 1e-2 m (chaos: small differences grow once the
character falls or its contacts change). docs/warp.md has the numbers of a run.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from workers.body.character import Character
from workers.motion.library import MotionLibrary
from workers.sim.warp_physics import WarpPhysics

SUBSTEPS = 16
THRESHOLDS = (1e-4, 1e-3, 1e-2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--control-steps", type=int, default=300)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    character = Character.load()
    model = character.model
    lib = MotionLibrary.load(character, ["humanoid3d_walk", "humanoid3d_run"], fps=30)
    clips, frames = np.array([0, 0, 1, 1]), np.array([5, 20, 3, 10])
    ref = lib.state(clips, frames)
    qpos, qvel = [*ref.qpos], [*ref.qvel]
    rng = np.random.default_rng(args.seed)
    for _ in range(2):
        q = model.qpos0.copy()
        mujoco.mj_integratePos(model, q, rng.normal(0.0, 0.5, model.nv), 0.3)
        qpos.append(q)
        qvel.append(rng.normal(0.0, 0.3, model.nv))
    qpos, qvel = np.array(qpos), np.array(qvel)
    n = len(qpos)
    names = [f"walk@{frames[0]}", f"walk@{frames[1]}", f"run@{frames[2]}", f"run@{frames[3]}", "fall-a", "fall-b"]

    sim = WarpPhysics(model, n, device=args.device)
    sim.set_state(range(n), qpos, qvel)
    datas = []
    for w in range(n):
        d = mujoco.MjData(model)
        d.qpos[:], d.qvel[:] = qpos[w], qvel[w]
        mujoco.mj_forward(model, d)
        datas.append(d)
    hold = character.qpos_to_action(qpos[len(clips) :])
    first = {t: [None] * n for t in THRESHOLDS}
    start = time.perf_counter()
    for step in range(1, args.control_steps + 1):
        ctrl = np.concatenate([lib.pd_targets(clips, frames + step), hold])
        sim.set_ctrl(ctrl)
        sim.step(SUBSTEPS)
        q_err, x_err = np.zeros(n), np.zeros(n)
        for w, d in enumerate(datas):
            d.ctrl[:] = ctrl[w]
            mujoco.mj_step(model, d, nstep=SUBSTEPS)
            mujoco.mj_step1(model, d)
            q_err[w] = np.abs(sim.qpos[w].cpu().numpy() - d.qpos).max()
            x_err[w] = np.abs(sim.xpos[w].cpu().numpy() - d.xpos).max()
            for t in THRESHOLDS:
                if first[t][w] is None and x_err[w] > t:
                    first[t][w] = step
        if step % 15 == 0 or step == args.control_steps:
            print(f"control step {step:4d} ({step / 30:5.2f} s)")
            for w in range(n):
                print(f"  {names[w]:8s} qpos {q_err[w]:.1e}  xpos {x_err[w]:.1e} m  root z {datas[w].qpos[2]:.2f} m")
    seconds = time.perf_counter() - start
    print(f"first control step with body positions off by more than ({', '.join(map(str, THRESHOLDS))}) m:")
    for w in range(n):
        print(f"  {names[w]:8s} " + "  ".join(str(first[t][w] or "-") for t in THRESHOLDS))
    print(f"overflowed: {sim.overflowed().tolist()}; {args.control_steps * SUBSTEPS * n / seconds:.0f} world-steps/s")


if __name__ == "__main__":
    main()
