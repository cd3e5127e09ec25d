"""Verdicts on a paper's statements from a sweep's seeds.

A statement is judged by a comparison fixed before the runs are read: which points it compares (named
in the statement, never the best one found) and the range the paper says their difference lies in,
d = mean(a) − mean(b) over seeds (or mean(a) alone, against levels). Our evidence is d's confidence
interval by Welch's t (`scipy.stats.ttest_ind(equal_var=False)`; `ttest_1samp` against a level),
at confidence 1 − 0.05 / m for a report of m statements (Bonferroni), so that a report's verdicts are
all right together at 95% at least, whatever the statements' dependence. A statement about a ratio
("about 3× longer") is judged on the ratio itself (`ratio=True`): Welch's interval of the difference of
the seeds' log values, exponentiated, which is the interval of the ratio of their geometric means.
Three verdicts only:

- reproduced:    the interval lies inside the paper's range;
- contradicted:  the interval lies outside it;
- not resolved:  the interval straddles its edge, or a side has fewer than two seeds, or no spread.
  With the paper's effect size E, "not resolved" says how many seeds per point would give the
  verdict "reproduced" with probability `POWER` (80%) if the true effect were E at the measured spread
  (`seeds_needed`, by the noncentral t; tests/unit/test_verdict.py checks it by simulation).

A statement that holds by construction (a quantity bounded by the setting that is swept) is not judged:
`by_construction` labels it, and it does not count among the m statements.

So a sweep whose points are equal up to noise is reported "not resolved" on every directional
statement in at least 95% of its repetitions (tests/unit/test_verdict.py shows it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

FAMILY_CONFIDENCE = 0.95
REPRODUCED, CONTRADICTED, NOT_RESOLVED = "reproduced", "contradicted", "not resolved"
LARGER, SMALLER = (0.0, math.inf), (-math.inf, 0.0)
MAX_SEEDS = 10_000
POWER = 0.8  # the chance of "reproduced" that "seeds needed" is sized for
BY_CONSTRUCTION = "holds by construction"


@dataclass(frozen=True)
class Judgement:
    verdict: str
    effect: float  # d, or mean(a) against a level
    low: float  # the confidence interval of d (NaN when none could be drawn)
    high: float
    confidence: float
    paper_effect: float | None = None  # the paper's effect size in d's units, where it gives one
    seeds_needed: int | None = None  # per point, to resolve the paper's effect at the measured spread
    why: str = ""  # why not resolved, when no interval could be drawn
    label: str = "d"  # "mean" when a statement is about one point's mean

    def text(self, fmt: str = ".3g", unit: str = "") -> str:
        """One cell: d (or the ratio) with its interval, and the verdict in bold."""
        if self.label == "ratio":  # no sign, a times sign instead of the unit
            fmt, unit, sign = ".2f", "×", ""
        else:
            sign = "+"
        said = f"{self.label} = {self.effect:{sign}{fmt}}{unit}" if math.isfinite(self.effect) else "n/a: not logged"
        if math.isfinite(self.low):
            said += f", {100 * self.confidence:.1f}% CI [{self.low:{sign}{fmt}}, {self.high:{sign}{fmt}}]{unit}"
        if self.why:
            said += f" ({self.why})"
        said += f": **{self.verdict}**"
        paper_effect = self.paper_effect
        if self.verdict == NOT_RESOLVED and paper_effect is not None and math.isfinite(self.low):
            if self.seeds_needed is None:
                said += f"; the paper's effect ({paper_effect:{fmt}}{unit}) cannot be sized from this spread"
            else:
                more = f"more than {MAX_SEEDS}" if self.seeds_needed > MAX_SEEDS else f"about {self.seeds_needed}"
                said += (
                    f"; {more} seeds per point would reproduce the paper's effect ({paper_effect:{fmt}}{unit}) "
                    f"{100 * POWER:.0f}% of the time"
                )
        return said


def claim_confidence(claims: int, family: float = FAMILY_CONFIDENCE) -> float:
    """Each interval's confidence for `claims` statements judged together (Bonferroni)."""
    return 1.0 - (1.0 - family) / max(claims, 1)


def judge(
    a: np.ndarray,
    b: np.ndarray | None,
    expected: tuple[float, float],
    claims: int,
    paper_effect: float | None = None,
    ratio: bool = False,
) -> Judgement:
    """The verdict on "d lies in `expected`", d = mean(a) − mean(b) over seeds, or with b None mean(a) itself
    (then `expected` holds levels of a). `claims`: how many statements the report judges. With `ratio`, the
    statement is about the ratio a / b of positive values: `expected` and `paper_effect` are ratios, and the
    effect and its interval are those of the ratio of the seeds' geometric means (Welch on the logs)."""
    if ratio:
        return _judge_ratio(np.asarray(a, float), np.asarray(b, float), expected, claims, paper_effect)
    a = np.asarray(a, float)
    confidence = claim_confidence(claims)
    two_sample = b is not None
    label = "d" if two_sample else "mean"
    if two_sample:
        b = np.asarray(b, float)
        effect = float(a.mean() - b.mean()) if len(a) and len(b) else math.nan
        small = min(len(a), len(b)) < 2
        flat = not small and _flat(a) and _flat(b)
    else:
        effect = float(a.mean()) if len(a) else math.nan
        small = len(a) < 2
        flat = not small and _flat(a)
    if small or flat:
        why = "fewer than two seeds on a side" if small else "the seeds' values are identical: no spread"
        return Judgement(NOT_RESOLVED, effect, math.nan, math.nan, confidence, paper_effect, why=why, label=label)
    if two_sample:
        ci = stats.ttest_ind(a, b, equal_var=False).confidence_interval(confidence)
    else:
        ci = stats.ttest_1samp(a, 0.0).confidence_interval(confidence)
    low, high = float(ci.low), float(ci.high)
    spread = a.var(ddof=1) + (b.var(ddof=1) if two_sample else 0.0)
    sides = 2 if two_sample else 1
    needed = seeds_needed(spread, paper_effect, confidence, sides, expected) if paper_effect is not None else None
    return Judgement(_verdict(low, high, expected), effect, low, high, confidence, paper_effect, needed, label=label)


def _verdict(low: float, high: float, expected: tuple[float, float]) -> str:
    lo, hi = expected
    if lo < low and high < hi:
        return REPRODUCED
    if high < lo or low > hi:
        return CONTRADICTED
    return NOT_RESOLVED


def _judge_ratio(
    a: np.ndarray, b: np.ndarray, expected: tuple[float, float], claims: int, paper_ratio: float | None
) -> Judgement:
    confidence = claim_confidence(claims)
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if (a <= 0).any() or (b <= 0).any():
        why = "a value is not positive: no ratio"
        return Judgement(NOT_RESOLVED, math.nan, math.nan, math.nan, confidence, paper_ratio, why=why, label="ratio")
    la, lb = np.log(a), np.log(b)
    effect = float(np.exp(la.mean() - lb.mean())) if len(a) and len(b) else math.nan
    small = min(len(a), len(b)) < 2
    if small or (_flat(la) and _flat(lb)):
        why = "fewer than two seeds on a side" if small else "the seeds' values are identical: no spread"
        return Judgement(NOT_RESOLVED, effect, math.nan, math.nan, confidence, paper_ratio, why=why, label="ratio")
    ci = stats.ttest_ind(la, lb, equal_var=False).confidence_interval(confidence)
    low, high = float(np.exp(ci.low)), float(np.exp(ci.high))
    needed = None
    if paper_ratio is not None:
        edges = tuple(math.log(e) if e > 0 else -math.inf for e in expected)
        needed = seeds_needed(la.var(ddof=1) + lb.var(ddof=1), math.log(paper_ratio), confidence, 2, edges)
    return Judgement(_verdict(low, high, expected), effect, low, high, confidence, paper_ratio, needed, label="ratio")


def _flat(v: np.ndarray) -> bool:
    """The seeds agree to rounding (equal values summed in another order): no spread to judge by."""
    return bool(np.ptp(v) <= 1e-9 * max(1.0, float(np.abs(v).max())))


def seeds_needed(
    spread: float,
    effect: float,
    confidence: float,
    sides: int = 2,
    expected: tuple[float, float] | None = None,
    power: float = POWER,
) -> int | None:
    """Seeds per point at which a true effect of `effect` at the measured spread (var_a + var_b; var_a alone
    with one side) would be reported "reproduced" — its interval inside `expected` (default: the side of zero
    the effect lies on) — with probability at least `power`. Each edge's chance is the noncentral t's (d̂'s
    distance to the edge over its standard error, sides·(n − 1) degrees of freedom); with two finite edges
    their chances less one, a lower bound on both together. None when the effect is zero, not finite, or not
    inside `expected`; MAX_SEEDS + 1 when more than MAX_SEEDS are needed."""
    if not math.isfinite(effect) or effect == 0 or not math.isfinite(spread) or spread < 0:
        return None
    lo, hi = expected if expected is not None else (LARGER if effect > 0 else SMALLER)
    if not lo < effect < hi:
        return None
    if spread == 0:
        return 2

    def chance(n: int) -> float:
        df = sides * (n - 1)
        t = stats.t.ppf(0.5 + confidence / 2, df)
        se = math.sqrt(spread / n)
        return 1.0 + sum(
            float(stats.nct.sf(t, df, g / se)) - 1.0 for g in (effect - lo, hi - effect) if math.isfinite(g)
        )

    if chance(MAX_SEEDS) < power:
        return MAX_SEEDS + 1
    low, high = 1, MAX_SEEDS  # the chance grows with n: chance(low) < power <= chance(high)
    while high - low > 1:
        mid = (low + high) // 2
        low, high = (low, mid) if chance(mid) >= power else (mid, high)
    return high


def by_construction(reason: str) -> str:
    """The verdict cell of a statement that holds by construction: not judged, and not counted."""
    return f"{BY_CONSTRUCTION} ({reason}): not judged"


def footnote(claims: int) -> str:
    """What a report's verdicts mean, for its reader."""
    return (
        f"Verdicts: d's confidence interval over seeds by Welch's t at {100 * claim_confidence(claims):.1f}% each "
        f"({claims} statements, Bonferroni: all right together at {100 * FAMILY_CONFIDENCE:.0f}%): “reproduced” "
        "when it lies inside the paper's range, “contradicted” when outside, else “not resolved”. "
        "A ratio's interval is that of the ratio of the seeds' geometric means (Welch on their logs). "
        f"Seeds needed: per point, for a {100 * POWER:.0f}% chance of “reproduced” were the paper's effect true "
        "at the measured spread. Each statement compares points fixed in advance.\n"
    )
