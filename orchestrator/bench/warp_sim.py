"""`bench sim --backend warp`: MuJoCo Warp on a device against MuJoCo C on all the machine's cores, interleaved.

For each world count N, the four sides below run in turn in blocks (`block_seconds`), the order reversed from
round to round so that a steady drift of the machine cancels; each round gives a Warp / MuJoCo C ratio and the
report is their median.

- warp: `WarpPhysics` with N worlds on the device (`--device cuda` or `cpu`), driven by an MLP of ControlVAE's
  size (s -> 3x512 ELU -> 28) evaluated on the device every control step. Everything of a control step stays
  on the device: the body states are read from MuJoCo Warp's arrays as zero-copy torch views (positions,
  rotations, and body velocities from `cvel` moved to each body's origin as `BatchedSim.kin_state` does),
  ControlVAE's state features s come from `workers.models.body_state.features` in torch, the MLP's targets
  are written into the controls view, and the K substeps run (one CUDA graph on a GPU where `WarpPhysics`
  captures it). Worlds whose root falls below `FALLEN_ROOT_M` are reset to reference states drawn from a
  pool on the device. That height test stands in for the simulator interface's contact test: it costs one
  small device-to-host copy a control step, and a reset recomputes every world's positions
  (`WarpPhysics.set_state`), so the figure includes both.
- physics only: the same worlds under constant controls, no policy: the simulator's own ceiling.
- interface: `WarpSim` (what `sim.backend=warp` runs in a rollout worker today) with N worlds, driven by the
  same MLP on the device, as a rollout worker's policy runs (`Policy.to`), through the simulator interface
  in NumPy: the state features s made on the device and copied to the host every control step
  (`StepResult.state`), copied back to the MLP, its actions copied back, falls found on the device and
  resets as the rollout worker has them (a worker beside MuJoCo Warp keeps the body states on the device
  and skips the first two copies: `bench host --sim warp` measures that path).
- cpu: `BatchedSim` (MuJoCo C, `mujoco.batch`) with `cpu_envs` environments stepped on `cpu_threads` threads
  (default every core), the same MLP on the CPU with as many torch threads, full simulator interface
  (features, contact falls, resets): `bench sim`'s batched side.

Rates are control steps per second summed over worlds; physics steps are K times that. The first Warp
step of a fresh environment compiles MuJoCo Warp's kernels (tens of seconds, cached afterwards): it runs in
an untimed warm-up block.
"""

from __future__ import annotations

import os
import platform
import time
from dataclasses import replace

import mujoco
import numpy as np
import torch

from orchestrator.bench.sim import BatchedRunner, make_mlp_policy, mlp, walk_run_setup
from workers.models import body_state
from workers.sim.env import BatchedSim, SimConfig, make_sim
from workers.sim.warp_physics import WarpPhysics

FALLEN_ROOT_M = 0.5  # root height below which a world counts as fallen and is reset
RESET_POOL = 4096  # reference start states kept on the device


class WarpRunner:
    """N worlds in MuJoCo Warp driven by the MLP on the device (or constant controls with `policy=False`)."""

    def __init__(self, character, library, nworld: int, device: str, substeps: int, seed: int, policy: bool):
        self.phys = WarpPhysics(character.model, nworld, device=device)
        self.k, self.nworld, self.policy = substeps, nworld, policy
        dev = self.phys.torch_device
        rng = np.random.default_rng(seed)
        clip, frame = library.sample_starts(RESET_POOL, rng)
        ref = library.state(clip, frame)
        self.pool_qpos = torch.as_tensor(ref.qpos, dtype=torch.float32, device=dev)
        self.pool_qvel = torch.as_tensor(ref.qvel, dtype=torch.float32, device=dev)
        self.gen = torch.Generator(device=dev).manual_seed(seed)
        self.net = mlp(16 * (character.model.nbody - 1) + 3, character.num_actions, seed).to(dev)
        self.hold = torch.as_tensor(character.qpos_to_action(ref.qpos[:1]), dtype=torch.float32, device=dev)
        self.reset(torch.arange(nworld, device=dev))
        self.control_steps = self.resets = 0

    def reset(self, ids: torch.Tensor) -> None:
        rows = torch.randint(0, RESET_POOL, (len(ids),), device=ids.device, generator=self.gen)
        self.phys.set_state(ids, self.pool_qpos[rows], self.pool_qvel[rows])

    def block(self, seconds: float) -> float:
        """Control steps per second (all worlds) over a block of `seconds` wall time."""
        phys, steps = self.phys, 0
        wall0 = time.perf_counter()
        while time.perf_counter() - wall0 < seconds:
            with torch.inference_mode():
                if self.policy:
                    phys.ctrl.copy_(self.net(body_state.features(phys.body_states())))
                else:
                    phys.ctrl.copy_(self.hold.expand(self.nworld, -1))
            phys.step(self.k)
            fallen = torch.nonzero(phys.qpos[:, 2] < FALLEN_ROOT_M).reshape(-1)
            if len(fallen):
                self.reset(fallen)
                self.resets += len(fallen)
            steps += 1
        if phys.torch_device.type == "cuda":
            torch.cuda.synchronize(phys.torch_device)
        self.control_steps += steps * self.nworld
        return steps * self.nworld / (time.perf_counter() - wall0)


def interleave(sides: dict, pairs: int, block_seconds: float) -> dict[str, np.ndarray]:
    """Rates of each side over `pairs` rounds, the sides' order reversed every other round."""
    names = list(sides)
    for name in names:  # untimed: kernel builds, caches, torch's first calls
        sides[name].block(block_seconds)
    rates = {name: [] for name in names}
    for p in range(pairs):
        for name in names if p % 2 == 0 else reversed(names):
            rates[name].append(sides[name].block(block_seconds))
    return {name: np.array(r) for name, r in rates.items()}


def run_worlds(
    character, library, nworld: int, device: str, config: SimConfig, cpu_envs: int, pairs: int, block_seconds, seed
) -> dict:
    k = config.substeps
    warp = WarpRunner(character, library, nworld, device, k, seed, policy=True)
    physics = WarpRunner(character, library, nworld, device, k, seed, policy=False)
    cpu_sim = BatchedSim(character, library, cpu_envs, config, seed=seed)
    cpu = BatchedRunner(cpu_sim, make_mlp_policy(cpu_sim.state_dim, cpu_sim.action_dim, seed))
    warp_sim = make_sim(character, library, nworld, replace(config, backend="warp", device=device), seed=seed)
    interface = BatchedRunner(warp_sim, make_mlp_policy(warp_sim.state_dim, warp_sim.action_dim, seed, device))
    sides = {"warp": warp, "physics": physics, "interface": interface, "cpu": cpu}
    rates = interleave(sides, pairs, block_seconds)
    ratios = rates["warp"] / rates["cpu"]
    out = {"worlds": nworld, "substeps": k}
    for name in sides:
        out[f"{name}_control_steps_per_s"] = float(np.median(rates[name]))
        out[f"{name}_physics_steps_per_s"] = float(np.median(rates[name])) * k
    out["ratio_to_cpu"] = float(np.median(ratios))
    out["ratio_quartiles"] = [float(q) for q in np.quantile(ratios, [0.25, 0.75])]
    out["warp_resets_per_control_step"] = warp.resets / max(warp.control_steps, 1) * nworld
    out["overflowed_worlds"] = int(warp.phys.overflowed().sum() + physics.phys.overflowed().sum())
    return out


def run(
    worlds: list[int],
    device: str = "cuda",
    seconds: float = 10.0,
    block_seconds: float = 0.5,
    sim_hz: float = 480.0,
    control_hz: float = 30.0,
    seed: int = 0,
    cpu_envs: int = 256,
    cpu_threads: int | None = None,
) -> dict:
    """Each world count: `seconds` of interleaved blocks of the four sides."""
    import warp

    cpu_threads = cpu_threads or os.cpu_count() or 1
    torch.set_num_threads(cpu_threads)
    character, library = walk_run_setup(sim_hz, control_hz)
    config = SimConfig(sim_hz=sim_hz, control_hz=control_hz, threads=cpu_threads)
    pairs = max(3, int(round(seconds / (4 * block_seconds))))
    gpu = torch.cuda.get_device_name() if device.startswith("cuda") else None
    return {
        "benchmark": "sim-warp",
        "machine": {"host": platform.node(), "cpus": os.cpu_count(), "gpu": gpu, "python": platform.python_version()},
        "versions": {"mujoco": mujoco.__version__, "warp": warp.__version__, "torch": torch.__version__},
        "device": device,
        "cpu_envs": cpu_envs,
        "cpu_threads": cpu_threads,
        "sim_hz": sim_hz,
        "control_hz": control_hz,
        "block_seconds": block_seconds,
        "pairs": pairs,
        "rows": [
            run_worlds(character, library, n, device, config, cpu_envs, pairs, block_seconds, seed) for n in worlds
        ],
    }


def format_table(r: dict) -> str:
    lines = [
        f"sim benchmark, MuJoCo Warp on {r['device']}{' (' + r['machine']['gpu'] + ')' if r['machine']['gpu'] else ''}"
        f" against MuJoCo C ({r['cpu_envs']} envs on {r['cpu_threads']} threads); {r['sim_hz']:g}/"
        f"{r['control_hz']:g} Hz; {r['pairs']} rounds of {r['block_seconds']:g} s blocks, sides interleaved",
        f"{'worlds':>8}  {'warp+MLP control/s':>19}{'physics/s':>14}{'physics only/s':>16}{'WarpSim control/s':>18}"
        f"{'C+MLP control/s':>17}{'warp/C':>8}{'IQR':>13}{'resets/step':>12}{'overflow':>9}",
    ]
    for x in r["rows"]:
        q1, q3 = x["ratio_quartiles"]
        lines.append(
            f"{x['worlds']:>8}  {x['warp_control_steps_per_s']:>19,.0f}{x['warp_physics_steps_per_s']:>14,.0f}"
            f"{x['physics_physics_steps_per_s']:>16,.0f}{x['interface_control_steps_per_s']:>18,.0f}"
            f"{x['cpu_control_steps_per_s']:>17,.0f}"
            f"{x['ratio_to_cpu']:>8.2f}{f'{q1:.2f}-{q3:.2f}':>13}{x['warp_resets_per_control_step']:>12.2f}"
            f"{x['overflowed_worlds']:>9}"
        )
    lines.append(
        "control/s: control steps per second summed over worlds (physics/s: x K substeps); warp/C: median over "
        "rounds of the Warp+MLP rate over MuJoCo C's with the same MLP; WarpSim: the simulator interface in NumPy (s "
        "made on the device, copied to the host and back to the MLP there; a rollout worker keeps its states on the "
        "device: bench host --sim warp); resets/step: worlds reset a control step"
    )
    return "\n".join(lines)
