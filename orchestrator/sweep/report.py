"""A sweep's comparison: tables and figures from its child runs, for the parent run.

- `final_table`: one row per point of the compared parameter, each final metric as
  mean ± std over seeds.
- `plot_final`: a bar per point and metric, each seed's value as a dot.
- `plot_curves`: learning curves against environment samples, the mean over seeds
  and a band from the lowest to the highest seed, one panel per metric.
- `curve_summary`: what a learning curve says in four numbers, for comparing
  with a paper's words ("fluctuates and is slower"): its final level (mean of the
  last tenth), its roughness (mean absolute change between consecutive logged
  values, over the range of the curve) and its speed, twice: the samples until it first
  reaches half of its final level above its start (a crossing, resolved only to the
  iteration it happens in), and the samples it takes to converge, ∫ (final − v(s)) /
  (final − v(0)) ds over the run (trapezoids over every logged value: τ for an
  exponential approach v = final·(1 − e^(−s/τ)), s₀ for a step at s₀), which every
  point of the curve moves, so it resolves a curve that crosses half of its level in the
  first iterations.

With `facet_by` (a second swept key, e.g. the terrain), each of these groups the runs
by (facet, compared value): the tables gain a column, `plot_final` a bar per pair and
`plot_curves` a row of panels per facet.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

History = list[tuple[int, float]]  # (step = samples, value)


def group(rows: list[dict[str, Any]], compare_by: str) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        out[str(r[compare_by])].append(r)
    return dict(sorted(out.items(), key=lambda kv: _sort_key(kv[0])))


def points(rows: list[dict[str, Any]], compare_by: str, facet_by: str | None = None) -> dict[tuple[str, ...], list]:
    """Rows by point: (value,) of `compare_by`, or (facet, value) with `facet_by`; facets, then values, in
    numeric order (with facet_by None, the order of `group`)."""
    keys = [facet_by, compare_by] if facet_by else [compare_by]
    out: dict[tuple[str, ...], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        out[tuple(str(r.get(k)) for k in keys)].append(r)
    return dict(sorted(out.items(), key=lambda kv: tuple(_sort_key(v) for v in kv[0])))


def _sort_key(value: str) -> tuple:
    try:
        return (0, float(value), "")
    except ValueError:
        return (1, 0.0, value)


def _values(rows: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.asarray([float(r[key]) for r in rows if r.get(key) is not None])


def final_table(
    rows: list[dict[str, Any]], compare_by: str, metrics: dict[str, str], facet_by: str | None = None
) -> str:
    columns = [facet_by, compare_by] if facet_by else [compare_by]
    lines = [
        "| " + " | ".join(columns) + " | seeds | " + " | ".join(metrics.values()) + " |",
        "|" + " --- |" * (len(columns) + 1 + len(metrics)),
    ]
    for point, members in points(rows, compare_by, facet_by).items():
        cells = []
        for key in metrics:
            v = _values(members, key)
            cells.append(f"{v.mean():.3f} ± {v.std():.3f}" if len(v) else "n/a")
        lines.append("| " + " | ".join(point) + f" | {len(members)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_final(
    rows: list[dict[str, Any]],
    compare_by: str,
    metrics: dict[str, str],
    path: Path,
    reference: dict[str, float] | None = None,
    facet_by: str | None = None,
) -> None:
    """reference: the paper's value of some metrics, drawn as a dashed line. With facet_by, a bar per
    (facet, value), coloured by facet."""
    groups = points(rows, compare_by, facet_by)
    names = ["\n".join(reversed(p)) for p in groups]  # the value, and the facet under it
    facets = list(dict.fromkeys(p[0] for p in groups))
    colours = [f"C{facets.index(p[0])}" if facet_by else "tab:blue" for p in groups]
    width = max(4.5, 0.6 * len(names)) if facet_by else 4.5
    fig = Figure(figsize=(width * len(metrics), 3.5))
    axes = np.atleast_1d(fig.subplots(1, len(metrics)))
    for ax, (key, label) in zip(axes, metrics.items(), strict=True):
        vals = [_values(members, key) for members in groups.values()]
        means = [v.mean() if len(v) else np.nan for v in vals]
        stds = [v.std() if len(v) else 0.0 for v in vals]
        ax.bar(np.arange(len(names)), means, yerr=stds, capsize=4, color=colours)
        ax.set_xticks(np.arange(len(names)), names)  # positions, not category strings that parse as numbers
        for i, v in enumerate(vals):
            ax.scatter([i] * len(v), v, color="black", s=10, zorder=3)
        if reference and key in reference:
            ax.axhline(reference[key], color="tab:red", linestyle="--", label=f"paper {reference[key]:g}")
            ax.legend(fontsize=8)
        ax.set_ylabel(label)
        ax.set_xlabel(f"{compare_by} / {facet_by}" if facet_by else compare_by)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def _on_grid(histories: list[History], grid: np.ndarray) -> np.ndarray:
    """Each history interpolated onto `grid` [G] (NaN beyond its last step): [n, G]."""
    out = np.full((len(histories), len(grid)), np.nan)
    for i, h in enumerate(histories):
        if h:
            steps, values = np.asarray(h, float).T
            inside = grid <= steps[-1]
            out[i, inside] = np.interp(grid[inside], steps, values)
    return out


def draw_curves(
    ax: Any,
    groups: dict[str, list[dict[str, Any]]],
    histories: dict[str, dict[str, History]],
    key: str,
    compare_by: str,
    colours: dict[str, str],
) -> None:
    """On `ax`, metric `key`'s curve per group: the mean over its runs and a band from the lowest to the highest."""
    for value, members in groups.items():
        hs = [histories.get(m["run_id"], {}).get(key, []) for m in members]
        last = max((h[-1][0] for h in hs if h), default=0)
        if not last:
            continue
        grid = np.linspace(0, last, 100)
        ys = _on_grid(hs, grid)
        ok = ~np.all(np.isnan(ys), axis=0)
        colour = colours[value]
        ax.plot(grid[ok], np.nanmean(ys[:, ok], axis=0), color=colour, label=f"{compare_by}={value}")
        if len(hs) > 1:
            ax.fill_between(grid[ok], np.nanmin(ys[:, ok], 0), np.nanmax(ys[:, ok], 0), color=colour, alpha=0.2)
    ax.set_xlabel("environment samples")


def plot_curves(
    rows: list[dict[str, Any]],
    histories: dict[str, dict[str, History]],
    compare_by: str,
    curves: dict[str, str],
    path: Path,
    facet_by: str | None = None,
) -> None:
    """rows carry run_id; histories[run_id][metric] is that run's history. With facet_by, a row of panels per
    facet; a compared value keeps its colour across them."""
    colours = {value: f"C{c % 10}" for c, value in enumerate(group(rows, compare_by))}
    facets = group(rows, facet_by) if facet_by else {"": rows}
    fig = Figure(figsize=(4.5 * len(curves), 3.5 * len(facets)))
    axes = fig.subplots(len(facets), len(curves), squeeze=False)
    for row_axes, (facet, members) in zip(axes, facets.items(), strict=True):
        for ax, (key, label) in zip(row_axes, curves.items(), strict=True):
            draw_curves(ax, group(members, compare_by), histories, key, compare_by, colours)
            ax.set_ylabel(label)
            if facet_by:
                ax.set_title(f"{facet_by} = {facet}", fontsize=9)
        row_axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def curve_summary(history: History) -> dict[str, float]:
    """{final, roughness, samples_to_half, samples_to_converge} of one learning curve (see the module docstring)."""
    if len(history) < 2:
        nan = float("nan")
        return {"final": nan, "roughness": nan, "samples_to_half": nan, "samples_to_converge": nan}
    steps, values = np.asarray(history, float).T
    tail = max(1, len(values) // 10)
    final = float(values[-tail:].mean())
    span = float(values.max() - values.min()) or 1.0
    roughness = float(np.mean(np.abs(np.diff(values))) / span)
    half = values[0] + 0.5 * (final - values[0])
    reached = np.flatnonzero(values >= half) if final >= values[0] else np.flatnonzero(values <= half)
    rise = final - values[0]
    remaining = (final - values) / rise if rise else np.zeros_like(values)
    return {
        "final": final,
        "roughness": roughness,
        "samples_to_half": float(steps[reached[0]]) if len(reached) else float("nan"),
        "samples_to_converge": float(np.trapezoid(remaining, steps)) if rise else float("nan"),
    }


def curve_table(
    rows: list[dict[str, Any]],
    histories: dict[str, dict[str, History]],
    compare_by: str,
    key: str,
    label: str,
    facet_by: str | None = None,
) -> str:
    """Per point, the summary of metric `key`'s curves as mean ± std over seeds."""
    columns = [facet_by, compare_by] if facet_by else [compare_by]
    lines = [
        "| " + " | ".join(columns) + f" | final {label} | roughness | samples to half of final | samples to converge |",
        "|" + " --- |" * (len(columns) + 4),
    ]
    for point, members in points(rows, compare_by, facet_by).items():
        s = [curve_summary(histories.get(m["run_id"], {}).get(key, [])) for m in members]
        cells = []
        for k in ("final", "roughness", "samples_to_half", "samples_to_converge"):
            v = np.asarray([x[k] for x in s], float)
            v = v[np.isfinite(v)]
            cells.append(f"{v.mean():.3g} ± {v.std():.2g}" if len(v) else "n/a")
        lines.append("| " + " | ".join(point) + " | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
