"""PhysicsVAE's α ablation as the paper shows it: Fig. 9, and its statements beside our numbers.

- `plot_spread`: per point, the mean of a per-rollout quantity with its spread over
  the rollouts (Fig. 9: time-until-fall mean and std over 100 rollouts), the runs of
  every seed pooled, each seed's mean as a dot; the compared values in numeric
  order, so α = 0 is on the left.
- `alpha_claims`, `kl_claims`: Sec. 5.5.1's statements as the paper states them (a ratio for "three
  times better"; β = 0 against the control arm β = 2 for the KL term), each a comparison fixed in
  advance, with its verdict (`orchestrator.sweep.verdict`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from orchestrator.sweep.report import group
from orchestrator.sweep.verdict import LARGER, NOT_RESOLVED, REPRODUCED, SMALLER, footnote, judge


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


# Sec. 5.5.1's statements, each a comparison fixed before the runs are read (`verdict`), named here before any
# run of the CPU scale was looked at: "the models trained with the simulation layer consistently performed
# three times better, where the best performances were shown in the values between 0.0003 to 0.003" is a
# ratio: the paper's best range pooled against no layer, judged on the ratio, "about 3x" read as 3 ×/÷ 1.5
# (2 to 4.5); the best range against the other α > 0; the largest against the centre of the best range.
CENTRE, BEST_RANGE, LARGE = 1e-3, (3e-4, 1e-3, 3e-3), 1e-2
THREE_X, ABOUT = 3.0, 1.5
THREE_X_RANGE = (THREE_X / ABOUT, THREE_X * ABOUT)
KL_LEVEL = 1.0  # "the characters fell within less than 1 second"


def _seeds(rows: list[dict[str, Any]], compare_by: str, key: str) -> dict[float, np.ndarray]:
    groups = group(rows, compare_by)
    return {float(v): np.asarray([r[key] for r in ms if r.get(key) is not None], float) for v, ms in groups.items()}


def _pool(seeds: dict[float, np.ndarray], values: Iterable[float]) -> np.ndarray:
    """Every run of the given points as one sample (conservative: the points' own differences add spread)."""
    parts = [seeds[v] for v in values if v in seeds]
    return np.concatenate(parts) if parts else np.zeros(0)


def _mean(v: np.ndarray) -> str:
    return f"{v.mean():.2f} s ({len(v)})" if len(v) else "n/a"


def alpha_claims(rows: list[dict[str, Any]], compare_by: str, key: str = "eval/time_until_fall_mean") -> str:
    """PhysicsVAE Sec. 5.5.1 beside ours (the no-KL statement is `kl_claims`'s, its own preset)."""
    seeds = _seeds(rows, compare_by, key)
    if not seeds:
        return ""
    zero = seeds.get(0.0, np.zeros(0))
    centre = seeds.get(CENTRE, np.zeros(0))
    inside = _pool(seeds, BEST_RANGE)
    outside = _pool(seeds, [a for a in seeds if a > 0 and a not in BEST_RANGE])
    large = seeds.get(LARGE, np.zeros(0))
    statements = [
        (f"with the simulation layer the controller lasts about 3x longer than without (ratio in "
         f"{THREE_X_RANGE[0]:g}-{THREE_X_RANGE[1]:g})",
         f"α in {{3e-4, 1e-3, 3e-3}}: {_mean(inside)} / α = 0: {_mean(zero)}", inside, zero, THREE_X_RANGE,
         THREE_X, True),
        ("the best α lies in 3e-4 … 3e-3",
         f"α in {{3e-4, 1e-3, 3e-3}}: {_mean(inside)} vs the other α > 0: {_mean(outside)}",
         inside, outside, LARGER, None, False),
        ("too large an α degrades",
         f"α = {LARGE:g}: {_mean(large)} vs α = {CENTRE:g}: {_mean(centre)}", large, centre, SMALLER, None, False),
    ]  # fmt: skip
    lines = ["| PhysicsVAE (Sec. 5.5.1, Fig. 9) | compared (mean time until fall, seeds) | verdict |",
             "| --- | --- | --- |"]  # fmt: skip
    for statement, compared, a, b, expected, effect, ratio in statements:
        j = judge(a, b, expected, len(statements), effect, ratio=ratio)
        lines.append(f"| {statement} | {compared} | {j.text('.2f', ' s')} |")
    lines.append("| without the KL term (β = 0) the character falls within 1 s | `+experiment=ablation_kl` | |")
    return "\n".join(lines) + "\n\n" + footnote(len(statements))


def kl_claims(rows: list[dict[str, Any]], compare_by: str, key: str = "eval/time_until_fall_mean") -> str:
    """Sec. 5.5.1: without the KL term (β = 0) the characters fell within 1 s, where with it (the control arm,
    the paper's β = 2) they stay up. Two statements: β = 0 falls sooner than β = 2 (the KL term is what keeps
    it up), and, only where that holds, within 1 s. The level alone is never the evidence: two arms that fall
    alike (an untrained controller, whatever β) are "not resolved" on both."""
    seeds = _seeds(rows, compare_by, key)
    off = seeds.get(0.0, np.zeros(0))
    controls = [v for v in seeds if v > 0]
    control = max(controls) if controls else None
    on = seeds.get(control, np.zeros(0)) if control is not None else np.zeros(0)
    claims = 2
    sooner = judge(off, on, SMALLER, claims, KL_LEVEL - on.mean() if len(on) and on.mean() > KL_LEVEL else None)
    lines = ["| PhysicsVAE (Sec. 5.5.1) | compared (mean time until fall, seeds) | verdict |", "| --- | --- | --- |"]
    arm = f"β = {control:g}" if control is not None else "β > 0: not swept"
    lines.append(f"| without the KL term the character falls sooner than with it | β = 0: {_mean(off)} vs "
                 f"{arm}: {_mean(on)} | {sooner.text('.2f', ' s')} |")  # fmt: skip
    if sooner.verdict == REPRODUCED:
        within = judge(off, None, (-math.inf, KL_LEVEL), claims).text(".2f", " s")
    else:
        within = (
            f"**{NOT_RESOLVED}** (not judged: β = 0 is not shown to fall sooner than {arm}, so its level alone "
            "says nothing of the KL term)"
        )
    lines.append(f"| ... within 1 s | β = 0: {_mean(off)} | {within} |")
    for value in controls:
        if value != control:
            lines.append(f"| (β = {value:g}) | {_mean(seeds[value])} | no claim |")
    return "\n".join(lines) + "\n\n" + footnote(claims)


CLAIMS = {"physicsvae_alpha": alpha_claims, "physicsvae_kl": kl_claims}
