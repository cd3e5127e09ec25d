"""The default run's learning speed on this machine: how long until it tracks and until it stays up.

The default config (`python -m orchestrator`, with any Hydra overrides given) is
trained for `minutes` of training wall time, with no iteration limit, tracking
off. Every `eval_every` seconds of training the loop pauses (the clock too) for
two evaluations of the current VAE weights:

- tracking error (ControlVAE Fig. 14 over 2-second segments, posterior mean z),
  by the run's own `eval` settings;
- time-until-fall (PhysicsVAE Fig. 9, z from the prior), over `fall_rollouts`
  rollouts capped at the run's `eval.fall_max_seconds`.

The result is the curve of both against training seconds and environment
samples, and for each level the first evaluation that reached it (tracking error
below 0.15 and 0.10 m, time-until-fall above 5 and 20 s): its seconds and
samples, or null when it was not reached within the budget.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from orchestrator.build import untracked_trainer
from orchestrator.compose import compose, validate
from orchestrator.world import evaluation_sim_config, load_library
from workers.evaluation.controller import time_until_fall, tracking_error
from workers.learners.vae import build_controller

# (metric, level, direction): reached when the metric is below (-1) or above (+1) the level.
LEVELS = (("tracking_error", 0.15, -1), ("tracking_error", 0.10, -1), ("time_until_fall", 5.0, 1),
          ("time_until_fall", 20.0, 1))  # fmt: skip


def evaluate(cfg, character, library, weights, fall_rollouts: int) -> dict[str, float]:
    controller = build_controller(character.num_bodies, character.num_actions, cfg.algo.vae)
    controller.load_state_dict(weights.state)
    track = tracking_error(
        controller, character, library, cfg.eval.tracking_seconds, evaluation_sim_config(cfg), cfg.seed
    )
    fall = time_until_fall(
        controller, character, library, fall_rollouts, cfg.eval.fall_max_seconds, sim_config=evaluation_sim_config(cfg),
        seed=cfg.seed,
    )  # fmt: skip
    return {"tracking_error": track["mean"], "time_until_fall": fall["mean"]}


def thresholds(curve: Sequence[dict[str, float]]) -> list[dict[str, Any]]:
    """Per level, the seconds and samples of the first point of the curve that reached it (else None)."""
    out = []
    for metric, level, sign in LEVELS:
        hit = next((p for p in curve if sign * (p[metric] - level) > 0), None)
        out.append(
            {
                "metric": metric,
                "level": level,
                "seconds": None if hit is None else hit["seconds"],
                "samples": None if hit is None else hit["samples"],
            }
        )
    return out


def run(
    minutes: float,
    eval_every: float,
    fall_rollouts: int,
    overrides: Sequence[str] = (),
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    budget = 60.0 * minutes
    with TemporaryDirectory() as tmp:
        cfg = validate(
            compose([*overrides, f"run_dir={tmp}", "tracking=off", "progress=false", "algo.loop.iterations=100000000"])
        )
        rt, trainer = untracked_trainer(cfg)
        character = trainer.character
        library = load_library(cfg, character)
        curve: list[dict[str, float]] = []
        try:
            trainer.method.start(trainer)
            trained = 0.0
            next_eval = 0.0
            while True:
                if trained >= next_eval or trained >= budget:
                    weights = rt.get(rt.call(trainer.handles["vae"], "get_weights"))
                    point = {"seconds": trained, "samples": trainer.state.samples, "iteration": trainer.state.iteration}
                    point.update(evaluate(cfg, character, library, weights, fall_rollouts))
                    curve.append(point)
                    if progress:
                        progress(
                            f"learning: {trained / 60:5.1f} min, {point['samples']:>9} samples: tracking error "
                            f"{point['tracking_error']:.3f} m, time-until-fall {point['time_until_fall']:.1f} s"
                        )
                    next_eval += eval_every
                    if trained >= budget:
                        break
                t0 = time.perf_counter()
                trainer.step()
                trained += time.perf_counter() - t0
            trainer.method.finish(trainer)
        finally:
            rt.shutdown()
    return {
        "benchmark": "learning",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "config": list(overrides) or ["(the default run)"],
        "minutes": minutes,
        "eval_every_s": eval_every,
        "fall_rollouts": fall_rollouts,
        "thresholds": thresholds(curve),
        "curve": curve,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    curve = result["curve"]
    fig = Figure(figsize=(11, 7))
    axes = fig.subplots(2, 2)
    for col, (x, label) in enumerate((("seconds", "training wall time (min)"), ("samples", "environment samples"))):
        xs = np.array([p[x] for p in curve], float) / (60.0 if x == "seconds" else 1.0)
        for row, (metric, unit) in enumerate((("tracking_error", "m"), ("time_until_fall", "s"))):
            ax = axes[row, col]
            ax.plot(xs, [p[metric] for p in curve], marker="o", ms=3)
            for _, level, _ in (lv for lv in LEVELS if lv[0] == metric):
                ax.axhline(level, color="grey", ls=":", lw=1)
            ax.set_xlabel(label)
            ax.set_ylabel(f"{metric.replace('_', ' ')} ({unit})")
    fig.suptitle(f"learning speed: {', '.join(result['config'])} ({result['machine']['cpus']} CPUs)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def format_table(result: dict[str, Any]) -> str:
    lines = [
        f"learning benchmark: {', '.join(result['config'])}, {result['minutes']:g} min of training, "
        f"{result['machine']['cpus']} CPUs",
        f"{'level':<24} {'seconds':>10} {'samples':>12}",
    ]
    for t in result["thresholds"]:
        op = "<" if t["metric"] == "tracking_error" else ">"
        name = f"{t['metric']} {op} {t['level']:g}"
        if t["seconds"] is None:
            lines.append(f"{name:<24} not reached in {result['minutes']:g} minutes")
        else:
            lines.append(f"{name:<24} {t['seconds']:>10.0f} {t['samples']:>12}")
    last = result["curve"][-1]
    lines.append(
        f"at the end: tracking error {last['tracking_error']:.3f} m, time-until-fall {last['time_until_fall']:.1f} s "
        f"({last['samples']} samples, {last['iteration']} iterations)"
    )
    if result.get("figure"):
        lines.append(f"figure: {result['figure']}")
    return "\n".join(lines)
