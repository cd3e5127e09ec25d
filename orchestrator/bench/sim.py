"""Simulation benchmark: raw MuJoCo stepping against the batched simulator.

All figures are single-threaded (MuJoCo steps on the calling thread; torch is
limited to one thread), so the ratio says how much of a core the simulator's own
Python work costs on top of the physics.

- raw: `mj_step` on one `MjData`, K substeps per call, timed around the call
  only. Same workload as the batched runs: Gaussian PD targets (σ = 0.1 rad)
  around the zero pose, a reference-state reset from the walk after a fall.
- batched, random policy: `BatchedSim.step` with the same targets, resets of
  finished environments included.
- batched, MLP policy: the targets come from an MLP of ControlVAE's size
  (s → 3×512 ELU → 28) evaluated on the whole batch each control step.
- ratio: the batched simulator's physics steps per second over the raw figure.
"""

from __future__ import annotations

import os
import platform
import time

import mujoco
import numpy as np

from workers.motion.library import MotionLibrary
from workers.sim.character import Character
from workers.sim.env import BatchedSim, SimConfig

NOISE = 0.1


def _setup(sim_hz: float, control_hz: float) -> tuple[Character, MotionLibrary]:
    character = Character.load(sim_hz=sim_hz)
    library = MotionLibrary.load(character, ["humanoid3d_walk"], fps=control_hz)
    return character, library


def raw_steps_per_second(character: Character, library: MotionLibrary, k: int, seconds: float, seed: int) -> float:
    m = character.model
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    start = library.state(np.array([0]), np.array([0]))

    def reset() -> None:
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = start.qpos[0], start.qvel[0]
        mujoco.mj_forward(m, d)

    reset()
    stepped, busy, wall0 = 0, 0.0, time.perf_counter()
    while time.perf_counter() - wall0 < seconds:
        d.ctrl[:] = rng.normal(0.0, NOISE, m.nu)
        t0 = time.perf_counter()
        mujoco.mj_step(m, d, nstep=k)
        busy += time.perf_counter() - t0
        stepped += k
        if d.qpos[2] < 0.5:
            reset()
    return stepped / busy


def batched_control_steps_per_second(sim: BatchedSim, policy, seconds: float) -> float:
    sim.reset()
    state = sim.reset()
    steps, wall0 = 0, time.perf_counter()
    while time.perf_counter() - wall0 < seconds:
        result = sim.step(policy(state))
        state = result.state
        done = np.flatnonzero(result.done)
        if done.size:
            state[done] = sim.reset(done)
        steps += 1
    return steps * sim.num_envs / (time.perf_counter() - wall0)


def make_mlp_policy(state_dim: int, action_dim: int, seed: int):
    import torch

    torch.manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(state_dim, 512), torch.nn.ELU(),
        torch.nn.Linear(512, 512), torch.nn.ELU(),
        torch.nn.Linear(512, 512), torch.nn.ELU(),
        torch.nn.Linear(512, action_dim),
    )  # fmt: skip
    net.eval()

    def policy(state: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return net(torch.from_numpy(state)).numpy()

    return policy


def run(envs: int, seconds: float, sim_hz: float, control_hz: float, seed: int = 0) -> dict:
    import torch

    torch.set_num_threads(1)
    character, library = _setup(sim_hz, control_hz)
    config = SimConfig(sim_hz=sim_hz, control_hz=control_hz)
    k = config.substeps
    raw = raw_steps_per_second(character, library, k, seconds, seed)
    sim = BatchedSim(character, library, envs, config, seed=seed)
    rng = np.random.default_rng(seed)

    def random_policy(state: np.ndarray) -> np.ndarray:
        return rng.normal(0.0, NOISE, (state.shape[0], sim.action_dim))

    random_cps = batched_control_steps_per_second(sim, random_policy, seconds)
    mlp_cps = batched_control_steps_per_second(sim, make_mlp_policy(sim.state_dim, sim.action_dim, seed), seconds)
    return {
        "benchmark": "sim",
        "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "versions": {"mujoco": mujoco.__version__, "torch": torch.__version__},
        "threads": 1,
        "envs": envs,
        "sim_hz": sim_hz,
        "control_hz": control_hz,
        "substeps": k,
        "seconds_per_measurement": seconds,
        "raw_physics_steps_per_s": raw,
        "random_policy": {
            "control_steps_per_s": random_cps,
            "physics_steps_per_s": random_cps * k,
            "physics_step_ratio": random_cps * k / raw,
        },
        "mlp_policy": {
            "control_steps_per_s": mlp_cps,
            "physics_steps_per_s": mlp_cps * k,
            "physics_step_ratio": mlp_cps * k / raw,
        },
    }


def format_table(r: dict) -> str:
    lines = [
        f"sim benchmark: {r['envs']} envs, {r['sim_hz']:g}/{r['control_hz']:g} Hz ({r['substeps']} substeps), "
        f"1 thread, {r['seconds_per_measurement']:g} s each",
        f"{'measurement':<28}{'control steps/s':>18}{'physics steps/s':>18}{'ratio to raw':>14}",
        f"{'raw mj_step':<28}{r['raw_physics_steps_per_s'] / r['substeps']:>18,.0f}"
        f"{r['raw_physics_steps_per_s']:>18,.0f}{1.0:>14.3f}",
    ]
    for key, label in (("random_policy", "batched, random policy"), ("mlp_policy", "batched, MLP 3x512 policy")):
        x = r[key]
        lines.append(
            f"{label:<28}{x['control_steps_per_s']:>18,.0f}{x['physics_steps_per_s']:>18,.0f}"
            f"{x['physics_step_ratio']:>14.3f}"
        )
    return "\n".join(lines)
