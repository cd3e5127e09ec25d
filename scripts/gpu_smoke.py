"""The GPU smoke's checks, in order, one line each: PASS, FAIL or SKIP, its seconds, and what it saw.

    python scripts/gpu_smoke.py --device cuda      # on the GPU machine (scripts/gpu-smoke.sh installs the wheels)
    python scripts/gpu_smoke.py --device cpu       # the dry run here: the same checks on the CPU and Warp's CPU device

Exit status 1 when a check fails (a SKIP is not a failure: it says what was not there to check). The checks:
devices (the driver, torch, Warp); a rollout worker with the VAE policy collecting on the device, beside MuJoCo Warp
there; every learner's eager update on the device and its state dict loaded into a CPU learner, equal to the last
bit; one compiled small learner; MuJoCo Warp on the device, its graph replayed against steps without one;
`tracking_error` with a CPU controller on a Warp simulator on the device (a goal made there); and short local training
runs of the methods that need no stage (`runtime=local tracking=off`, learners and MuJoCo Warp on the device; in the
dry run MuJoCo C, as Warp's CPU device would take minutes). The methods built on stages (PhysicsVAE, PULSE, the task
policies) read them from MLflow, which does not fit in the call beside Warp. Where warp-lang is not installed, the
checks that need it SKIP, and the rollout and training run beside MuJoCo C.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class Skip(Exception):
    """A check with nothing to check here; the message says what is missing."""


def has_warp() -> bool:
    try:
        import mujoco_warp  # noqa: F401
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


def devices(device: str) -> str:
    seen = [f"torch {torch.__version__}"]
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise RuntimeError("torch sees no GPU")
        seen.append(f"{torch.cuda.get_device_name(0)} (torch sees {torch.cuda.device_count()})")
        smi = shutil.which("nvidia-smi")
        if smi:
            out = subprocess.run([smi, "--query-gpu=driver_version", "--format=csv,noheader"], capture_output=True)
            seen.append(f"driver {out.stdout.decode().strip()}")
    if has_warp():
        import warp

        warp.config.quiet = True
        warp.init()
        count = warp.get_cuda_device_count()
        seen.append(f"warp {warp.__version__} sees {count} CUDA device(s)")
        if device.startswith("cuda") and count == 0:
            raise RuntimeError(f"{'; '.join(seen)}: Warp sees no GPU where torch does (its CUDA 13 needs R580+)")
    else:
        seen.append("warp not installed")
    return "; ".join(seen)


def character_and_clip():
    from workers.body.character import Character
    from workers.motion.library import MotionLibrary

    character = Character.load()
    return character, MotionLibrary.load(character, ["humanoid3d_walk"], fps=30)


def rollout(device: str) -> str:
    from workers.learners.vae import VAEConfig
    from workers.policies import VAEPolicy
    from workers.rollout import RolloutWorker
    from workers.sim.env import SimConfig

    character, library = character_and_clip()
    sim = SimConfig(backend="warp", device=device) if has_warp() else SimConfig()
    policy = VAEPolicy(character.num_bodies, character.num_actions, VAEConfig(latent_dim=16)).to(device)
    worker = RolloutWorker(character, library, 8, policy, sim_config=sim, seed=0)
    trajectory = worker.collect(30)
    if not np.isfinite(trajectory.next_states).all():
        raise RuntimeError("the collected states went non-finite")
    engine = f"MuJoCo Warp on {device}" if has_warp() else "MuJoCo C (no warp-lang)"
    return f"{trajectory.actions.shape[0]} steps of 8 environments, the policy on {policy.device}, {engine}"


def learners(device: str) -> str:
    from orchestrator.bench.learners import BUILDERS, cpu_seeded

    done = []
    for name, build in BUILDERS.items():
        with cpu_seeded(0):
            case = build("small", torch.Generator().manual_seed(0), torch.device(device))
        metrics = case.learner.update(case.batch)
        state = case.learner.state_dict()
        with cpu_seeded(0):
            twin = build("small", torch.Generator().manual_seed(0), torch.device("cpu")).learner
        twin.load_state_dict(state)
        for key, value in twin.get_weights().state.items():
            if not torch.equal(value, case.learner.get_weights().state[key]):
                raise RuntimeError(f"{name}: {key} differs once loaded on the CPU")
        loss = next((v for k, v in metrics.items() if "loss" in k), None)
        done.append(f"{name} {loss:.3g}" if isinstance(loss, float) else name)
    return "eager updates, state dicts loaded on the CPU: " + ", ".join(done)


def compiled(device: str) -> str:
    from orchestrator.bench.learners import BUILDERS, cpu_seeded

    with cpu_seeded(0):
        case = BUILDERS["world_model"]("small", torch.Generator().manual_seed(0), torch.device(device))
    case.learner.compile("default")
    losses = [case.learner.update(case.batch) for _ in range(3)]
    values = [v for m in losses for k, v in m.items() if "loss" in k]
    if not values or not np.isfinite(values).all():
        raise RuntimeError(f"compiled world model's losses: {values}")
    return f"world model (small) compiled, 3 updates, loss {values[-1]:.3g}"


def warp_graph(device: str) -> str:
    if not has_warp():
        raise Skip("warp-lang is not installed (carry .device/smoke)")
    test = ROOT / "tests" / "unit" / "test_warp_physics.py"
    env = {**os.environ, "MOCAP_WARP_DEVICE": device, "PYTHONPATH": os.pathsep.join([*sys.path, str(ROOT)])}
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-m", "", "-p", "no:cacheprovider", str(test), "-k", "graph"],
        capture_output=True, text=True, env=env, cwd=ROOT,
    )  # fmt: skip
    last = (proc.stdout.strip().splitlines() or ["no output"])[-1]
    if proc.returncode != 0:
        raise RuntimeError(f"{last}\n{proc.stdout[-2000:]}")
    return f"graph capture and replay against eager steps: {last}"


def tracking_on_warp(device: str) -> str:
    if not has_warp():
        raise Skip("warp-lang is not installed (carry .device/smoke)")
    from workers.evaluation.controller import tracking_error
    from workers.learners.vae import VAEConfig, build_controller
    from workers.sim.base import SimConfig

    character, library = character_and_clip()
    controller = build_controller(character.num_bodies, character.num_actions, VAEConfig(latent_dim=16)).eval()
    result = tracking_error(controller, character, library, 0.5, SimConfig(backend="warp", device=device))
    value = next(iter(result.values()))
    return f"a CPU controller on a Warp simulator on {device}: {len(result)} values, first {value:.3g}"


def training(device: str) -> str:
    if importlib_missing("hydra", "omegaconf"):
        raise Skip("hydra-core or omegaconf is not installed (carry .device/smoke)")
    done = []
    on_warp = device.startswith("cuda") and has_warp()
    engine = ["sim.backend=warp", f"sim.device={device}"] if on_warp else []
    with tempfile.TemporaryDirectory() as tmp:
        for algo in ("controlvae", "tracker", "amp"):
            command = [
                sys.executable, "-m", "orchestrator", f"algo={algo}", "scale=smoke", "motion=walk", "runtime=local",
                "tracking=off", "progress=false", "eval.video=false", "algo.loop.iterations=2",
                f"runtime.learner_device={device}", f"run_dir={Path(tmp) / algo}", *engine,
            ]  # fmt: skip
            t0 = time.perf_counter()
            proc = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
            if proc.returncode != 0:
                raise RuntimeError(f"{algo}: exit {proc.returncode}: {proc.stderr.strip()[-1500:]}")
            done.append(f"{algo} {time.perf_counter() - t0:.0f} s")
    where = f"MuJoCo Warp on {device}" if on_warp else "MuJoCo C"
    return f"2 iterations each, learners on the device, {where}: " + ", ".join(done)


def importlib_missing(*names: str) -> bool:
    import importlib.util

    return any(importlib.util.find_spec(n) is None for n in names)


CHECKS: list[tuple[str, Callable[[str], str]]] = [
    ("devices", devices),
    ("rollout", rollout),
    ("learners", learners),
    ("compiled", compiled),
    ("warp-graph", warp_graph),
    ("tracking-on-warp", tracking_on_warp),
    ("training", training),
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="cuda (the GPU machine) or cpu (the dry run)")
    parser.add_argument("--only", default="", help="comma-separated checks to run (default: all)")
    args = parser.parse_args(argv)
    wanted = set(filter(None, args.only.split(",")))
    failed, t_all = 0, time.perf_counter()
    for name, check in CHECKS:
        if wanted and name not in wanted:
            continue
        t0 = time.perf_counter()
        try:
            said, verdict = check(args.device), "PASS"
        except Skip as e:
            said, verdict = str(e), "SKIP"
        except Exception as e:  # noqa: BLE001 - every check reports, the next one still runs
            said, verdict = f"{type(e).__name__}: {e}", "FAIL"
            failed += 1
        print(f"{verdict} {name} ({time.perf_counter() - t0:.1f} s): {said}", flush=True)
    print(f"{'FAIL' if failed else 'PASS'} all on {args.device} ({time.perf_counter() - t_all:.0f} s, {failed} failed)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
