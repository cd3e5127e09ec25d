"""Verdicts on a paper's statements from a sweep's seeds.

A statement is judged by a comparison fixed before the runs are read: which points it compares (named
in the statement, never the best one found) and the range the paper says their difference lies in,
d = mean(a) − mean(b) over seeds (or mean(a) alone, against levels). Our evidence is d's confidence
interval by Welch's t (`scipy.stats.ttest_ind(equal_var=False)`; `ttest_1samp` against a level),
at confidence 1 − 0.05 / m for a report of m statements (Bonferroni), so that a report's verdicts are
all right together at 95% at least, whatever the statements' dependence. Three verdicts only:

- reproduced:    the interval lies inside the paper's range;
- contradicted:  the interval lies outside it;
- not resolved:  the interval straddles its edge, or a side has fewer than two seeds, or no spread.
  With the paper's effect size E, "not resolved" says how many seeds per point the measured spread
  would need for the interval's half-width to fall below |E|.

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
        """One cell: d with its interval, and the verdict in bold."""
        said = f"{self.label} = {self.effect:+{fmt}}{unit}" if math.isfinite(self.effect) else "n/a: not logged"
        if math.isfinite(self.low):
            said += f", {100 * self.confidence:.1f}% CI [{self.low:+{fmt}}, {self.high:+{fmt}}]{unit}"
        if self.why:
            said += f" ({self.why})"
        said += f": **{self.verdict}**"
        paper_effect = self.paper_effect
        if self.verdict == NOT_RESOLVED and paper_effect is not None and math.isfinite(self.low):
            if self.seeds_needed is None:
                said += f"; the paper's effect ({paper_effect:{fmt}}{unit}) cannot be sized from this spread"
            else:
                more = f"more than {MAX_SEEDS}" if self.seeds_needed > MAX_SEEDS else f"about {self.seeds_needed}"
                said += f"; {more} seeds per point would resolve the paper's effect ({paper_effect:{fmt}}{unit})"
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
) -> Judgement:
    """The verdict on "d lies in `expected`", d = mean(a) − mean(b) over seeds, or with b None mean(a) itself
    (then `expected` holds levels of a). `claims`: how many statements the report judges."""
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
    lo, hi = expected
    if lo < low and high < hi:
        verdict = REPRODUCED
    elif high < lo or low > hi:
        verdict = CONTRADICTED
    else:
        verdict = NOT_RESOLVED
    spread = a.var(ddof=1) + (b.var(ddof=1) if two_sample else 0.0)
    sides = 2 if two_sample else 1
    needed = seeds_needed(spread, paper_effect, confidence, sides) if paper_effect is not None else None
    return Judgement(verdict, effect, low, high, confidence, paper_effect, needed, label=label)


def _flat(v: np.ndarray) -> bool:
    """The seeds agree to rounding (equal values summed in another order): no spread to judge by."""
    return bool(np.ptp(v) <= 1e-9 * max(1.0, float(np.abs(v).max())))


def seeds_needed(spread: float, effect: float, confidence: float, sides: int = 2) -> int | None:
    """Seeds per point for which t · sqrt(spread / n) < |effect|: the interval's half-width at the measured
    spread (var_a + var_b; var_a alone with one side) drops below the effect, so an effect that size would be
    resolved (t with sides·(n − 1) degrees of freedom). None when the effect is zero or not finite;
    MAX_SEEDS + 1 when more than MAX_SEEDS are needed."""
    if not math.isfinite(effect) or effect == 0 or not math.isfinite(spread):
        return None
    n = np.arange(2, MAX_SEEDS + 1)
    resolved = stats.t.ppf(0.5 + confidence / 2, sides * (n - 1)) * np.sqrt(spread / n) < abs(effect)
    return int(n[resolved.argmax()]) if resolved.any() else MAX_SEEDS + 1


def footnote(claims: int) -> str:
    """What a report's verdicts mean, for its reader."""
    return (
        f"Verdicts: d's confidence interval over seeds by Welch's t at {100 * claim_confidence(claims):.1f}% each "
        f"({claims} statements, Bonferroni: all right together at {100 * FAMILY_CONFIDENCE:.0f}%): “reproduced” "
        "when it lies inside the paper's range, “contradicted” when outside, else “not resolved”. "
        "Each statement compares points fixed in advance.\n"
    )
