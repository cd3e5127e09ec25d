"""PhysicsVAE's α ablation as the paper shows it: Fig. 9, and its statements beside our numbers.

- `plot_spread`: per point, the mean of a per-rollout quantity with its spread over
  the rollouts (Fig. 9: time-until-fall mean and std over 100 rollouts), the runs of
  every seed pooled, each seed's mean as a dot; the compared values in numeric
  order, so α = 0 is on the left.
- `alpha_claims`: a table of Sec. 5.5.1's statements, each with what our runs say.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from orchestrator.sweep.report import group


def pooled(members: list[dict[str, Any]], mean_key: str, std_key: str) -> tuple[float, float]:
    """Mean and std over all rollouts of runs with equal rollout counts, from each run's mean and std."""
    m = np.asarray([r[mean_key] for r in members if r.get(mean_key) is not None], float)
    s = np.asarray([r[std_key] for r in members if r.get(std_key) is not None], float)
    if not len(m):
        return float("nan"), float("nan")
    if len(s) != len(m):
        return float(m.mean()), float("nan")
    mean = m.mean()
    return float(mean), float(np.sqrt(max(np.mean(s**2 + m**2) - mean**2, 0.0)))


def plot_spread(
    rows: list[dict[str, Any]],
    compare_by: str,
    mean_key: str,
    std_key: str,
    label: str,
    path: Path,
    title: str = "",
    level: tuple[float, str] | None = None,
) -> None:
    """level: a value drawn across the figure with its label (the expert's own time until fall)."""
    groups = group(rows, compare_by)
    names = list(groups)
    stats = [pooled(groups[n], mean_key, std_key) for n in names]
    fig = Figure(figsize=(max(4.5, 1.0 * len(names) + 2), 3.6))
    ax = fig.subplots()
    x = np.arange(len(names))
    ax.errorbar(
        x,
        [s[0] for s in stats],
        yerr=[s[1] for s in stats],
        fmt="o-",
        capsize=5,
        color="tab:blue",
        label="mean ± std over rollouts (seeds pooled)",
    )
    for i, n in enumerate(names):
        seeds = [r[mean_key] for r in groups[n] if r.get(mean_key) is not None]
        ax.scatter([i] * len(seeds), seeds, color="black", s=12, zorder=3, label="a seed's mean" if i == 0 else None)
    if level is not None and np.isfinite(level[0]):
        ax.axhline(level[0], color="tab:gray", linestyle="--", label=level[1])
    ax.set_xticks(x, names)
    ax.set_xlabel(compare_by)
    ax.set_ylabel(label)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def alpha_claims(rows: list[dict[str, Any]], compare_by: str, key: str = "eval/time_until_fall_mean") -> str:
    """PhysicsVAE Sec. 5.5.1 beside ours: the layer's gain, the best α, large α, (no KL: its own preset)."""
    groups = group(rows, compare_by)
    seeds = {float(v): np.asarray([r[key] for r in ms if r.get(key) is not None], float) for v, ms in groups.items()}
    means = {a: float(v.mean()) if len(v) else float("nan") for a, v in seeds.items()}
    if not means:
        return ""

    def versus(a: float, b: float) -> str:
        """Whether two points differ by more than twice the standard error of their difference over seeds."""
        x, y = seeds[a], seeds[b]
        if len(x) < 2 or len(y) < 2:
            return "one seed: no spread to compare with"
        se = float(np.sqrt(x.var(ddof=1) / len(x) + y.var(ddof=1) / len(y)))
        verdict = "beyond" if abs(means[a] - means[b]) > 2 * se else "within"
        return f"difference {means[a] - means[b]:+.2f} s, {verdict} 2 standard errors over seeds ({2 * se:.2f} s)"

    lines = ["| PhysicsVAE (Sec. 5.5.1, Fig. 9) | ours |", "| --- | --- |"]
    zero = means.get(0.0)
    positive = {a: m for a, m in means.items() if a > 0 and np.isfinite(m)}
    if zero is not None and positive:
        best_a = max(positive, key=positive.get)
        ratio = positive[best_a] / zero if zero > 0 else float("nan")
        lines.append(
            f"| with the simulation layer (α > 0) the controller lasts about 3x longer than without (α = 0) | "
            f"best α > 0: {positive[best_a]:.2f} s vs α = 0: {zero:.2f} s, {ratio:.2f}x; {versus(best_a, 0.0)} |"
        )
        inside = 3e-4 <= best_a <= 3e-3
        others = sorted((a for a in means if a != best_a and np.isfinite(means[a])), key=means.get, reverse=True)
        runner = f"; runner-up α = {others[0]:g}: {versus(best_a, others[0])}" if others else ""
        where = "inside" if inside else "outside"
        lines.append(f"| the best α lies in 3e-4 … 3e-3 | best α = {best_a:g} ({where}){runner} |")
        largest = max(positive)
        if largest != best_a:
            lines.append(
                f"| too large an α degrades | α = {largest:g}: {positive[largest]:.2f} s, "
                f"{positive[largest] / positive[best_a]:.2f} of the best; {versus(largest, best_a)} |"
            )
        else:
            lines.append(f"| too large an α degrades | the largest α ({largest:g}) is the best here: not seen |")
    lines.append("| without the KL term (β = 0) the character falls within 1 s | `+experiment=ablation_kl` |")
    return "\n".join(lines) + "\n"


def kl_claims(rows: list[dict[str, Any]], compare_by: str, key: str = "eval/time_until_fall_mean") -> str:
    groups = group(rows, compare_by)
    lines = ["| PhysicsVAE (Sec. 5.5.1) | ours |", "| --- | --- |"]
    for value, ms in groups.items():
        m = np.mean([r[key] for r in ms if r.get(key) is not None] or [np.nan])
        if float(value) == 0.0:
            lines.append(f"| without the KL term (β = 0) the character falls within 1 s | β = 0: {m:.2f} s |")
        else:
            lines.append(f"| (with the KL term, β = {value}) | {m:.2f} s |")
    return "\n".join(lines) + "\n"


CLAIMS = {"physicsvae_alpha": alpha_claims, "physicsvae_kl": kl_claims}
