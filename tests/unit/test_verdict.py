"""Verdicts on the papers' statements: Welch intervals worked by hand, the Bonferroni correction, the seeds a
paper's effect would need, and null sweeps reported "not resolved" at the rate the reports claim."""

from __future__ import annotations

import math

import numpy as np
import pytest

from orchestrator.sweep.physicsvae import alpha_claims, kl_claims
from orchestrator.sweep.tasks import prior_claims
from orchestrator.sweep.verdict import (
    CONTRADICTED,
    LARGER,
    NOT_RESOLVED,
    REPRODUCED,
    SMALLER,
    claim_confidence,
    judge,
    seeds_needed,
)

HIGH, LOW = np.array([1.0, 1.1, 0.9]), np.array([0.0, 0.1, -0.1])


def test_welch_interval_worked_by_hand():
    # d = 1.0; each side's variance (ddof 1) 0.01, so SE = sqrt(0.01/3 + 0.01/3) = 0.08165 and Welch's
    # degrees of freedom (2 · (0.01/3)²)⁻¹ · (0.02/3)² = 4; t(0.975, 4) = 2.7764: 1.0 ± 0.2267.
    j = judge(HIGH, LOW, LARGER, claims=1)
    assert j.verdict == REPRODUCED and j.effect == pytest.approx(1.0)
    assert (j.low, j.high) == (pytest.approx(0.77330, abs=1e-5), pytest.approx(1.22670, abs=1e-5))
    assert judge(LOW, HIGH, LARGER, claims=1).verdict == CONTRADICTED
    assert judge(LOW, HIGH, SMALLER, claims=1).verdict == REPRODUCED
    # Three statements: each at 1 - 0.05/3; t(1 - 0.05/6, 4) = 3.9608, so 1.0 ± 0.3234.
    three = judge(HIGH, LOW, LARGER, claims=3)
    assert three.confidence == pytest.approx(1 - 0.05 / 3) == claim_confidence(3)
    assert three.low == pytest.approx(1 - 3.96079 * 0.0816497, abs=1e-4)
    assert "98.3% CI [+0.677, +1.323]" in three.text(".3f") and three.text().endswith("**reproduced**")


def test_an_interval_across_the_edge_is_not_resolved_and_says_what_would_resolve_it():
    # d = 0.1 against variances 0.5 a side: not resolved. With a paper effect of 1.0 the measured spread
    # (0.5 + 0.5) needs n with t(0.975, 2n - 2) · sqrt(1/n) < 1: n = 5 gives 2.306 · 0.447 = 1.03, n = 6 gives
    # 2.228 · 0.408 = 0.91.
    j = judge(np.array([0.5, 1.5]), np.array([0.4, 1.4]), LARGER, claims=1, paper_effect=1.0)
    assert j.verdict == NOT_RESOLVED and j.seeds_needed == 6
    assert "about 6 seeds per point would resolve the paper's effect (1)" in j.text()
    assert seeds_needed(1.0, 1.0, 0.95) == 6 and seeds_needed(1.0, 0.0, 0.95) is None
    # A margin: "a larger σ succeeds by less than 0.1 more" holds when the whole interval is below 0.1.
    assert judge(np.array([0.80, 0.84]), np.array([0.80, 0.82]), (-math.inf, 0.1), claims=1).verdict == NOT_RESOLVED
    tight = judge(np.array([0.81, 0.82, 0.83]), np.array([0.80, 0.81, 0.82]), (-math.inf, 0.1), claims=1)
    assert tight.verdict == REPRODUCED


def test_one_sample_against_a_level_and_the_cases_without_an_interval():
    # mean 0.5, sd 0.1, n = 3: 0.5 ± 4.303 · 0.0577 = [0.252, 0.748], all below 1 s.
    j = judge(np.array([0.4, 0.5, 0.6]), None, (-math.inf, 1.0), claims=1)
    assert j.verdict == REPRODUCED and j.text(".2f", " s").startswith("mean = +0.50 s, 95.0% CI [+0.25, +0.75] s")
    assert judge(np.array([3.0, 4.0, 5.0]), None, (-math.inf, 1.0), claims=1).verdict == CONTRADICTED
    one = judge(np.array([1.0]), LOW, LARGER, claims=1)
    assert one.verdict == NOT_RESOLVED and "fewer than two seeds" in one.text()
    # Seeds sharing one skill stage give identical values: nothing to judge by, whatever the difference.
    same = judge(np.array([0.1, 0.1, 0.1]), np.array([0.3, 0.3, 0.3]), SMALLER, claims=1)
    assert same.verdict == NOT_RESOLVED and "identical" in same.text()
    assert judge(np.array([]), LOW, LARGER, claims=1).text().startswith("n/a: not logged")


def _resolved(table: str) -> int:
    return table.count(f"**{REPRODUCED}**") + table.count(f"**{CONTRADICTED}**")


def test_a_null_sweep_is_not_resolved_at_the_rate_the_reports_claim():
    """Six α (and three priors) equal up to noise, three seeds each, 1000 times: a report says "reproduced"
    or "contradicted" anywhere in at most 5% of them (its footnote's family-wise 95%). The former rule,
    beyond 2 standard errors with the best α picked after looking, said "beyond" in about 16%."""
    rng = np.random.default_rng(0)
    alphas = (0.0, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2)
    trials, alpha_hits, prior_hits = 1000, 0, 0
    for _ in range(trials):
        rows = [{"a": a, "seed": s, "m": 5.0 + rng.normal()} for a in alphas for s in range(3)]
        alpha_hits += _resolved(alpha_claims(rows, "a", key="m")) > 0
        keys = ("skill/random_sampling_fell", "eval/task_return", "eval/task_success", "eval/time_until_fall_mean")
        priors = [
            {"p": p, "seed": s, **{k: rng.normal() for k in keys}}
            for p in ("standard_normal", "conditional", "learned")
            for s in range(3)
        ]
        prior_hits += _resolved(prior_claims(priors, "p")) > 0
    bound = 0.05 + 3 * math.sqrt(0.05 * 0.95 / trials)
    assert alpha_hits / trials <= bound and prior_hits / trials <= bound
    assert "all right together at 95%" in alpha_claims(rows, "a", key="m")


def test_a_real_effect_is_reproduced_and_the_kl_level_is_judged():
    """α = 1e-3 lasts 3x as long as α = 0 with tight seeds: the fixed comparison reproduces it."""
    rows = []
    for a, t in ((0.0, 1.0), (1e-4, 2.0), (3e-4, 3.0), (1e-3, 3.0), (3e-3, 3.0), (1e-2, 1.5)):
        rows += [{"a": a, "seed": s, "m": t + 0.05 * (s - 1)} for s in range(3)]
    lines = alpha_claims(rows, "a", key="m").splitlines()
    assert "α = 0.001: 3.00 s (3) vs α = 0: 1.00 s (3)" in lines[2] and lines[2].endswith("**reproduced** |")
    assert "α in {3e-4, 1e-3, 3e-3}: 3.00 s (9) vs the other α > 0: 1.75 s (6)" in lines[3]
    assert lines[4].startswith("| too large an α degrades") and lines[4].endswith("**reproduced** |")
    kl = kl_claims(
        [{"b": b, "seed": s, "m": t + 0.1 * s} for b, t in ((0.0, 0.4), (2.0, 9.0)) for s in range(3)], "b", "m"
    )
    assert "β = 0) the character falls within 1 s | 0.50 s (3) | mean = +0.50 s" in kl and "**reproduced**" in kl


def test_amps_gradient_penalty_statements_compare_no_penalty_with_amps_weight():
    """Fig. 8 judged on w_gp = 0 against 10 only (the other points are ignored): a rougher curve without the
    penalty is reproduced; equal speeds up to noise are not resolved."""
    from orchestrator.sweep.amp import gp_claims

    rough = {0.0: [0.50, 0.52, 0.51], 1.0: [0.9, 0.9, 0.9], 10.0: [0.10, 0.11, 0.12], 40.0: [0.0, 0.0, 0.0]}
    speed = {0.0: [4000, 6000, 5000], 1.0: [1, 1, 1], 10.0: [5200, 4800, 5600], 40.0: [9e9, 9e9, 9e9]}
    rows = [
        {"algo.discriminator.w_gp": str(w), "seed": i, "curve/roughness": r, "curve/samples_to_half": s}
        for w in rough
        for i, (r, s) in enumerate(zip(rough[w], speed[w], strict=True))
    ]
    text = gp_claims(rows, "algo.discriminator.w_gp")
    fluctuates, slower = (line for line in text.splitlines() if line.startswith("| without") or "slower" in line)
    assert "w_gp = 0: 0.51 (3) vs w_gp = 10: 0.11 (3)" in fluctuates and "**reproduced**" in fluctuates
    assert "**not resolved**" in slower
    assert "97.5% CI" in text  # two statements, Bonferroni


def test_seeds_equal_to_rounding_have_no_spread():
    """Three seeds that fall at the same step (means equal but for the order of a float sum) give no interval:
    not resolved, never a zero-width interval read as contradicted."""
    a = np.array([1.1, 1.1000000000000003, 1.0999999999999999])
    j = judge(a, None, (-np.inf, 1.0), 1)
    assert j.verdict == NOT_RESOLVED and "no spread" in j.why
    assert judge(a, a + 2e-16, LARGER, 1).verdict == NOT_RESOLVED
