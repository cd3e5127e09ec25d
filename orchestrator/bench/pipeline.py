"""End-to-end throughput of the training loop for every method: local against Ray, with 1…N rollout workers.

Each measurement builds a method's components at the given scale (tracking off)
with the given runtime and worker count, runs warm-up iterations, then times
`iterations` loop steps (collect → replay or learners → update → publish →
report) and reports environment samples per second and learner updates
(optimiser steps, summed over the learners) per second. Start-up and
evaluation are not timed.
"""

from __future__ import annotations

import os
import platform
import time
from tempfile import TemporaryDirectory
from typing import Any

from orchestrator.build import untracked_trainer
from orchestrator.compose import compose, validate


def _updates(metrics: dict[str, float]) -> float:
    """Optimiser steps so far, summed over the learners (each reports its weights' version)."""
    return sum(v for k, v in metrics.items() if k.endswith("/version") and not k.startswith("rollout/"))


def measure(
    algo: str,
    scale: str,
    runtime: str,
    workers: int,
    iterations: int,
    warmup: int,
    envs: int,
    seed: int,
    sim: str = "mujoco",
    sim_device: str = "cpu",
) -> dict[str, Any]:
    with TemporaryDirectory() as tmp:
        overrides = [
            f"algo={algo}",
            f"scale={scale}",
            "motion=walk",
            f"runtime={runtime}",
            f"runtime.rollout_workers={workers}",
            f"runtime.envs_per_worker={envs}",
            f"run_dir={tmp}",
            "tracking=off",
            "progress=false",
            f"seed={seed}",
            f"sim.backend={sim}",
            f"sim.device={sim_device if sim == 'warp' else 'cpu'}",  # MuJoCo C runs on the CPU only
        ]
        if "warmup" in compose(overrides).algo.loop:  # a replay-fed method learns from its first collection
            overrides.append("algo.loop.warmup=0")
        cfg = validate(compose(overrides))
        rt, trainer = untracked_trainer(cfg)
        try:
            trainer.method.start(trainer)
            metrics: dict[str, float] = {}
            for _ in range(warmup):
                metrics = trainer.step()
            s0, u0 = trainer.state.samples, _updates(metrics)
            t0 = time.perf_counter()
            for _ in range(iterations):
                metrics = trainer.step()
            elapsed = time.perf_counter() - t0
            samples = trainer.state.samples - s0
            updates = _updates(metrics) - u0
            trainer.method.finish(trainer)
        finally:
            rt.shutdown()
    return {
        "algo": algo,
        "sim": sim if sim == "mujoco" else f"{sim}:{sim_device}",
        "scale": scale,
        "runtime": runtime,
        "workers": workers,
        "envs_per_worker": envs,
        "iterations": iterations,
        "seconds": elapsed,
        "samples_per_s": samples / elapsed,
        "updates_per_s": updates / elapsed,
    }


def run(
    algos: list[str],
    scale: str,
    runtimes: list[str],
    workers: list[int],
    iterations: int,
    warmup: int,
    envs: int,
    seed: int,
    progress=None,
    sims: tuple[str, ...] = ("mujoco",),
    sim_device: str = "cpu",
) -> dict[str, Any]:
    """Each method, runtime and worker count on each simulator engine (`sims`: mujoco and/or warp, the latter on
    `sim_device`), one after another."""
    results = []
    for algo in algos:
        for rt in runtimes:
            for n in workers:
                for sim in sims:
                    if progress:
                        progress(f"pipeline: {algo} on {rt} with {n} rollout worker(s), sim {sim}...")
                    results.append(measure(algo, scale, rt, n, iterations, warmup, envs, seed, sim, sim_device))
    return {
        "benchmark": "pipeline",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "preset": f"scale={scale}, motion=walk (tracking off)",
        "results": results,
    }


def format_table(result: dict[str, Any]) -> str:
    lines = [f"pipeline benchmark: {result['preset']}, {result['machine']['cpus']} CPUs"]
    lines.append(
        f"{'algo':<11} {'sim':<10} {'runtime':<8} {'workers':>7} {'envs/worker':>11} {'samples/s':>10} "
        f"{'updates/s':>10} {'seconds':>8}"
    )
    for r in result["results"]:
        lines.append(
            f"{r['algo']:<11} {r.get('sim', 'mujoco'):<10} {r['runtime']:<8} {r['workers']:>7} "
            f"{r['envs_per_worker']:>11} {r['samples_per_s']:>10.0f} "
            f"{r['updates_per_s']:>10.1f} {r['seconds']:>8.1f}"
        )
    return "\n".join(lines)
