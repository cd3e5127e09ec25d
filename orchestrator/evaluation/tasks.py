"""A task run's evaluation in the loop: `workers.evaluation.tasks` on the current task policy, as metrics, JSON
and a figure (the reward over time, and the roots' paths with their goals)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

from orchestrator.evaluation.protocols import Progress, jsonable
from orchestrator.schema import Config
from orchestrator.tracking.base import RunLogger
from orchestrator.world import evaluation_sim_config
from workers.body.character import Character
from workers.evaluation.tasks import evaluate_task_policy
from workers.motion.library import MotionLibrary
from workers.task.policy import TaskRolloutPolicy


def evaluate_task(
    cfg: Config,
    character: Character,
    library: MotionLibrary,
    policy: TaskRolloutPolicy,
    logger: RunLogger,
    iteration: int,
    final: bool,
) -> dict[str, float]:
    """eval/task_return, eval/task_success, eval/style_deviation_deg, eval/time_until_fall_mean, eval/task_fell
    and each loss term's mean (eval/task_<term>), over `eval.task_goals` fixed goals of `eval.task_seconds`."""
    with Progress(cfg, 1) as progress, progress.phase("task episodes"):
        result = evaluate_task_policy(
            policy,
            character,
            library,
            cfg.eval.task_goals,
            cfg.eval.task_seconds,
            sim_config=evaluation_sim_config(cfg),
            seed=cfg.eval.task_goal_seed,
        )
    metrics = {
        "eval/task_return": result["return"],
        "eval/task_success": result["success"],
        "eval/style_deviation_deg": result["style_deviation_deg"],
        "eval/time_until_fall_mean": result["time_until_fall_mean"],
        "eval/task_fell": result["fell"],
    }
    if "success_pulse" in result:  # VR tracking: PULSE's rule alone, without our no-fall clause
        metrics["eval/task_success_pulse"] = result["success_pulse"]
    metrics.update({f"eval/task_{k}": float(v) for k, v in result["terms"].items()})
    name = "final" if final else f"iter-{iteration:07d}"
    report = {k: v for k, v in result.items() if k not in ("roots", "goals")}
    logger.log_dict(jsonable({"iteration": iteration, "policy_version": policy.version, **report}), f"eval/{name}.json")
    task = cfg.algo.task
    title = f"{task.task} on {cfg.terrain.kind} ground, σ = {task.sigma:g}, policy version {policy.version}"
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / f"task-{name}.png"
        plot_task_eval(result, task.task, png, title)
        logger.log_artifact(str(png), "eval")
    return metrics


def plot_task_eval(result: dict[str, Any], task: str, path: Path, title: str) -> None:
    from matplotlib.figure import Figure  # imported when a figure is drawn: the benchmarks draw none

    fig = Figure(figsize=(10, 4))
    a, b = fig.subplots(1, 2)
    a.plot(result["curve_t"], result["curve"], color="tab:blue")
    a.set_ylim(0, 1.02)
    a.set_xlabel("time (s)")
    a.set_ylabel("task reward e^(-L_g), episodes still up")
    a.set_title(
        f"return {result['return']:.3f}, success {result['success']:.0%}, "
        f"{result['fell']:.0%} fell, style {result['style_deviation_deg']:.1f}°",
        fontsize=9,
    )
    roots, goals = result["roots"], result["goals"]
    for e in range(roots.shape[1]):
        line = b.plot(roots[:, e, 0], roots[:, e, 1], lw=0.8)[0]
        if task == "point_goal":
            b.scatter(goals[:, e, 0], goals[:, e, 1], s=12, marker="x", color=line.get_color())
    b.set_aspect("equal", adjustable="datalim")
    b.set_xlabel("x (m)")
    b.set_ylabel("y (m)")
    b.set_title("root paths" + (" and their targets (x)" if task == "point_goal" else ""), fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
