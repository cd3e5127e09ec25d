"""The GPU check, ready for a machine that has one: the learners on CUDA beside the same on the CPU.

    make device-wheels                 # here, with network: mujoco and its import-time dependencies as wheels
    sh scripts/device-check.sh         # there: installs those wheels beside the tree, runs this module

It needs torch (with CUDA), numpy and mujoco only: nothing on its import path reads ray, mlflow or hydra
(`tests/unit/test_bench_device.py` checks that). It prints, for each device:

- `bench learners` at every size: paper, laptop, small (updates/s, GFLOP/s, share of the update's own
  matmuls and of the device's dense-GEMM peak);
- one paper-size ControlVAE iteration's learner updates: `algo_scale/controlvae_paper.yaml` collects 2,048
  states an iteration and trains the world model 8 times on 512 windows of 8 steps and the VAE 8 times on
  512 rollouts of 24 steps (replay ratios 16 and 48), so an iteration's updates are 8 + 8 of
  `bench learners`' paper-size world-model and VAE updates; the time of those 16 (after one of each to
  warm up) and the ratio of the CPU's to the GPU's;
- on the GPU, unless `--compile off`: the learners again at `--compile-sizes` (default small) with their
  losses through `torch.compile` (default mode "reduce-overhead": CUDA graphs, which pay where an update
  is many small kernels), their compile time, and the compiled / eager ratio of updates/s, each against
  an eager twin timed in the same rounds. A compile that fails (no Triton, no C compiler) is reported
  and the rest of the check stands. At the paper sizes the world model's and the VAE's compiles take
  minutes (their rollouts unroll into one graph): an H200 had not finished them in 60 and 125 s.
"""

from __future__ import annotations

import os
import platform
import time
from typing import Any

import torch

from orchestrator.bench import learners as bench_learners
from orchestrator.bench.matmuls import sync
from workers.learners.base import cpu_seeded

ITERATION_UPDATES = {"world_model": 8, "vae": 8}  # ControlVAE's epoch at scale=paper (see the docstring)


def paper_iteration(device: torch.device, seed: int = 0) -> dict[str, Any]:
    """Seconds of one paper-size ControlVAE iteration's learner updates on `device`, per learner and in all."""
    out: dict[str, Any] = {}
    for name, count in ITERATION_UPDATES.items():
        gen = torch.Generator().manual_seed(seed)
        with cpu_seeded(seed):
            case = bench_learners.BUILDERS[name]("paper", gen, device)
            case.learner.update(case.batch)  # warm-up (allocator, cuBLAS, thread pool)
            sync(device)
            t0 = time.perf_counter()
            for _ in range(count):
                case.learner.update(case.batch)
            sync(device)
            out[f"{name}_s"] = time.perf_counter() - t0
    out["iteration_s"] = sum(out[f"{n}_s"] for n in ITERATION_UPDATES)
    return out


def run(
    devices: list[str],
    seconds: float = 3.0,
    threads: int | None = None,
    progress=None,
    compile_mode: str = "reduce-overhead",
    compile_sizes: tuple[str, ...] = ("small",),
) -> dict[str, Any]:
    for dev in devices:  # a GPU that is not there is refused before anything runs
        bench_learners.resolve_device(dev, "--devices")
    if threads:
        torch.set_num_threads(threads)
    result: dict[str, Any] = {
        "benchmark": "device",
        "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "devices": {},
    }
    for dev in devices:
        learners = bench_learners.run(seconds=seconds, progress=progress, device=dev)
        if progress:
            progress(f"paper-size ControlVAE iteration on {dev} ...")
        resolved = bench_learners.resolve_device(dev, "--devices")
        result["devices"][dev] = {"learners": learners, "paper_iteration": paper_iteration(resolved)}
        if dev == "cuda" and compile_mode != "off":
            if progress:
                progress(f"learners compiled ({compile_mode}, {'/'.join(compile_sizes)}) on {dev} ...")
            try:
                compiled = bench_learners.run(
                    sizes=list(compile_sizes), seconds=seconds, progress=progress, device=dev, compile_mode=compile_mode
                )
            except Exception as e:  # noqa: BLE001 - a failed compile is a finding, not the end of the check
                compiled = {"error": f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"}
            result["devices"][dev]["compiled"] = compiled
    return result


def format_report(r: dict[str, Any]) -> str:
    lines = [f"device check: torch {r['torch']}, {r['threads']} CPU thread(s), {r['machine']['cpus']} cores"]
    for dev, x in r["devices"].items():
        lines += ["", bench_learners.format_table(x["learners"])]
        it = x["paper_iteration"]
        lines.append(
            f"paper-size ControlVAE iteration on {dev}: world model 8 updates {it['world_model_s']:.2f} s, "
            f"VAE 8 updates {it['vae_s']:.2f} s, {it['iteration_s']:.2f} s in all"
        )
        compiled = x.get("compiled")
        if compiled and "error" in compiled:
            lines.append(f"compiled learners on {dev}: failed ({compiled['error']})")
        elif compiled:
            lines += ["", bench_learners.format_table(compiled)]  # each row: compiled / eager, same rounds
    if {"cpu", "cuda"} <= set(r["devices"]):
        cpu, gpu = (r["devices"][d]["paper_iteration"]["iteration_s"] for d in ("cpu", "cuda"))
        lines.append(f"paper-size iteration, CPU / GPU: {cpu:.2f} s / {gpu:.2f} s = {cpu / gpu:.1f}x")
    return "\n".join(lines)
