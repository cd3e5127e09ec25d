"""AMP's gradient-penalty statements (Fig. 8) beside our numbers, each a comparison fixed in advance.

"Without the gradient penalty, training fluctuates and is slower to converge" is two statements about the
learning curve of the first reported curve (`ppo/episode_return`), each comparing w_gp = 0 with AMP's own
w_gp = 10 over seeds (`orchestrator.sweep.verdict`): its roughness (`report.curve_summary`: the mean
absolute change between logged values over the curve's range) is larger without the penalty, and so is the
number of samples it takes to converge (`curve_summary`'s ∫ (final − v) / (final − v₀) ds, which every logged
value moves: at the laptop scale the return crosses half of its final level in the 2nd or 3rd of 80 iterations,
so the crossing cannot tell two curves apart). The curve summaries reach the rows as `curve/roughness` and
`curve/samples_to_converge` (`orchestrator.sweep.callback`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orchestrator.sweep.report import group
from orchestrator.sweep.verdict import LARGER, footnote, judge

NONE, AMPS = 0.0, 10.0  # no penalty, and AMP's Table 4 weight


def _values(rows: list[dict[str, Any]], compare_by: str, key: str) -> dict[float, np.ndarray]:
    out = {}
    for value, members in group(rows, compare_by).items():
        v = np.asarray([r.get(key, np.nan) for r in members], float)
        out[float(value)] = v[np.isfinite(v)]
    return out


def _mean(x: np.ndarray, fmt: str) -> str:
    return f"{x.mean():{fmt}} ({len(x)})" if len(x) else "n/a"


def gp_claims(rows: list[dict[str, Any]], compare_by: str) -> str:
    statements = [
        ("without the gradient penalty, training fluctuates", "curve/roughness", "roughness of the return curve",
         ".3g", ""),
        ("... and is slower to converge", "curve/samples_to_converge",
         "samples to converge, ∫ (final − R) / (final − R₀) ds", ".3g", " samples"),
    ]  # fmt: skip
    lines = ["| AMP (Fig. 8) | compared (seeds) | verdict |", "| --- | --- | --- |"]
    for statement, key, what, fmt, unit in statements:
        v = _values(rows, compare_by, key)
        a, b = v.get(NONE, np.zeros(0)), v.get(AMPS, np.zeros(0))
        j = judge(a, b, LARGER, len(statements))
        compared = f"{what}: w_gp = 0: {_mean(a, fmt)} vs w_gp = 10: {_mean(b, fmt)}"
        lines.append(f"| {statement} | {compared} | {j.text(fmt, unit)} |")
    return "\n".join(lines) + "\n\n" + footnote(len(statements))


CLAIMS = {"amp_gp": gp_claims}
