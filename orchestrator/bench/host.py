"""`bench host`: what a rollout worker does besides the physics, per control step, at many environments.

A worker on MuJoCo Warp hands the physics to the device, but the rest of its control step
still runs on the host in NumPy: the body states and their features, the reference
lookups, the terminations, the recorders' rewards and Φ(s), the resets, the trajectory's
arrays, plus the policy's inference on `--device`. This benchmark runs the real
`RolloutWorker` (collect calls, everything it records) on a simulator whose physics does
nothing (`FrozenSim`: the bodies stay where the last reset put them, so tracking failures
and clip ends still reset environments as they do in training), and splits each control step
into the policy's networks and the rest. The rest is the host's ceiling: a worker cannot
collect faster than `envs / host seconds per step` control steps a second, however fast its
GPU steps the physics.

With `--sim warp` the frozen simulator is MuJoCo Warp's (`FrozenWarpSim`, on `--device` with
the policy): the body states, features, rewards, reference lookups and actions then stay on the
device and the trajectory is copied once per collect, as a worker on MuJoCo Warp does (what the
host still does is the reference bookkeeping, terminations and resets); with `--sim mujoco` (the
default) it is MuJoCo C's, all on the host.

The networks' time is measured with hooks around the modules of the policy's networks (nested
calls counted once), with the device synchronised at both ends on a GPU.
"""

from __future__ import annotations

import os
import platform
import time

import numpy as np
import torch

from orchestrator.bench.rollout import make_worker
from orchestrator.bench.sim import walk_run_setup
from workers.learners.vae import ControlVAEObjective, state_weight_vector
from workers.recorders import TrackingReward
from workers.rollout import RolloutWorker
from workers.sim.env import BatchedSim, SimConfig

POLICIES = ("vae", "vae-paper", "actor-critic", "tracker", "task")
SIMS = ("mujoco", "warp")


class FrozenSim(BatchedSim):
    """MuJoCo C's simulator with no physics: a control step leaves every body where it is, and nothing falls."""

    def _advance(self, actions: np.ndarray) -> None:
        pass

    def _contact_falls(self) -> np.ndarray:
        return np.zeros(self.num_envs, bool)


class NetworkClock:
    """Seconds spent inside a policy's networks: forward hooks on every module in them (the containers, which are
    never called, aside), the outermost call only. Policies call their networks' methods (`act`, `encode`), not
    their forward, and those reach modules at any depth (a ModuleDict's MLPs, say)."""

    def __init__(self, modules: list[torch.nn.Module], device: torch.device):
        self.seconds, self.depth, self.device, self._start = 0.0, 0, device, 0.0
        self.handles = []
        containers = (torch.nn.ModuleDict, torch.nn.ModuleList)
        for net in modules:
            for module in net.modules():
                if not isinstance(module, containers):
                    self.handles.append(module.register_forward_pre_hook(self._enter))
                    self.handles.append(module.register_forward_hook(self._leave))

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _enter(self, *_) -> None:
        if self.depth == 0:
            self._sync()
            self._start = time.perf_counter()
        self.depth += 1

    def _leave(self, *_) -> None:
        self.depth -= 1
        if self.depth == 0:
            self._sync()
            self.seconds += time.perf_counter() - self._start


def frozen_warp_sim(character, library, envs: int, device: str, seed: int):
    """MuJoCo Warp's simulator on `device` with no physics (the controls are set, no step is taken)."""
    from workers.sim.warp_sim import WarpSim

    class FrozenWarpSim(WarpSim):
        def _advance(self, actions: np.ndarray) -> None:
            self.physics.set_ctrl(actions)

        def _contact_falls(self) -> np.ndarray:
            return np.zeros(self.num_envs, bool)

    return FrozenWarpSim(character, library, envs, SimConfig(backend="warp", device=device), seed=seed)


def frozen_worker(
    kind: str, character, library, envs: int, device: str, seed: int, sim: str = "mujoco"
) -> RolloutWorker:
    worker = make_worker(kind, character, library, 1, SimConfig(), seed)  # the policy and recorders of `kind`
    recorders = worker.recorders
    if kind.startswith("vae"):  # ControlVAE's worker records its tracking reward (orchestrator/algos/controlvae.py)
        weights = state_weight_vector(character.num_bodies, ControlVAEObjective().state_weights).numpy()
        recorders = [TrackingReward(weights)]
    if sim == "warp":
        frozen_sim = frozen_warp_sim(character, library, envs, device, seed)
    else:
        frozen_sim = FrozenSim(character, library, envs, SimConfig(), seed=seed)
    frozen = RolloutWorker(character, library, envs, worker.policy, seed=seed, recorders=recorders, sim=frozen_sim)
    frozen.policy.to(device)
    return frozen


def measure(worker: RolloutWorker, steps: int, collect: int) -> dict:
    """Control steps of the worker, timed in all and inside its policy's networks."""
    clock = NetworkClock(worker.policy.networks(), worker.policy.device)
    worker.collect(collect)  # warm-up: first calls allocate
    clock.seconds = 0.0
    done, wall0 = 0, time.perf_counter()
    while done < steps:
        worker.collect(collect)
        done += collect
    wall = time.perf_counter() - wall0
    for h in clock.handles:
        h.remove()
    m = worker.num_envs
    host = wall - clock.seconds
    return {
        "envs": m,
        "control_steps": done,
        "ms_per_step": 1e3 * wall / done,
        "network_ms_per_step": 1e3 * clock.seconds / done,
        "host_ms_per_step": 1e3 * host / done,
        "control_steps_per_s": m * done / wall,
        "host_ceiling_control_steps_per_s": m * done / host,
    }


def run(
    policies: list[str],
    envs: list[int],
    steps: int,
    collect: int,
    device: str,
    threads: int,
    seed: int,
    sims: tuple[str, ...] = ("mujoco",),
) -> dict:
    torch.set_num_threads(threads)
    character, library = walk_run_setup(480.0, 30.0)
    rows = []
    for kind in policies:
        for m in envs:
            for sim in sims:  # side by side, per size
                worker = frozen_worker(kind, character, library, m, device, seed, sim)
                rows.append({"policy": kind, "sim": sim, **measure(worker, steps, collect)})
    return {
        "benchmark": "host",
        "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "device": device,
        "threads": threads,
        "collect": collect,
        "results": rows,
    }


def format_table(r: dict) -> str:
    lines = [
        f"host benchmark: one rollout worker with no physics, policy on {r['device']}, {r['threads']} torch "
        f"thread(s), collect({r['collect']})",
        f"{'policy':<13}{'sim':<8}{'envs':>7}{'ms/step':>9}{'network ms':>12}{'host ms':>9}{'control/s':>11}"
        f"{'host ceiling/s':>16}",
    ]
    for x in r["results"]:
        lines.append(
            f"{x['policy']:<13}{x.get('sim', 'mujoco'):<8}{x['envs']:>7}{x['ms_per_step']:>9.1f}"
            f"{x['network_ms_per_step']:>12.1f}"
            f"{x['host_ms_per_step']:>9.1f}{x['control_steps_per_s']:>11,.0f}{x['host_ceiling_control_steps_per_s']:>16,.0f}"
        )
    return "\n".join(lines)
