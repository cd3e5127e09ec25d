"""The sweep report: tables and curve summaries with known answers."""

from __future__ import annotations

import math

import pytest

from orchestrator.sweep import report


def test_curve_summary_of_a_ramp_and_of_a_noisy_curve():
    # A ramp 0, 1, ..., 9 over steps 0, 100, ..., 900: the last tenth is the last point (9);
    # half of the rise from 0 to 9 is 4.5, first reached at value 5 (step 500); every change is 1,
    # over a range of 9: roughness 1/9.
    ramp = [(100 * i, float(i)) for i in range(10)]
    s = report.curve_summary(ramp)
    assert s["final"] == 9.0 and s["samples_to_half"] == 500.0
    assert math.isclose(s["roughness"], 1 / 9)
    # The same rise with alternating steps back is rougher and reaches half later.
    zigzag = [(100 * i, float(i if i % 2 == 0 else i - 2)) for i in range(10)]
    z = report.curve_summary(zigzag)
    assert z["roughness"] > s["roughness"]
    assert math.isnan(report.curve_summary([(0, 1.0)])["final"])  # one point is no curve
    # The ramp's remaining fraction falls linearly from 1 at step 0 to 0 at step 900: half of 900.
    assert s["samples_to_converge"] == pytest.approx(450.0)


def test_samples_to_converge_resolves_curves_that_cross_half_their_level_at_once():
    """Exponential approaches with τ = 4,000 and τ = 5,500 samples, logged every 4096 samples over 80 iterations
    (an AMP laptop run): both cross half of their final level at the first logged step (1 − e^(−4096/5500) =
    0.53), so samples to half is 4096 for both; the samples to converge are τ to within the grid's trapezoid
    error (2048·coth(2048/τ): 4,330 and 5,760)."""
    import numpy as np

    steps = 4096 * np.arange(81)
    for tau in (4e3, 5.5e3):
        curve = [(int(s), float(1 - np.exp(-s / tau))) for s in steps]
        summary = report.curve_summary(curve)
        assert summary["samples_to_half"] == 4096.0
        assert summary["samples_to_converge"] == pytest.approx(tau, rel=0.1)
    step = [(int(s), 0.0 if s < 40_000 else 2.0) for s in steps]  # a step between 36,864 and 40,960
    assert report.curve_summary(step)["samples_to_converge"] == pytest.approx(36_864 + 2048)


def test_final_table_groups_seeds_and_orders_points_numerically():
    rows = [
        {"w": "10.0", "seed": "0", "m": 1.0, "run_id": "a"},
        {"w": "10.0", "seed": "1", "m": 3.0, "run_id": "b"},
        {"w": "2.0", "seed": "0", "m": 5.0, "run_id": "c"},
    ]
    table = report.final_table(rows, "w", {"m": "metric"}).splitlines()
    assert table[2] == "| 2.0 | 1 | 5.000 ± 0.000 |"  # 2 before 10: numeric order
    assert table[3] == "| 10.0 | 2 | 2.000 ± 1.000 |"  # mean and population std over seeds


def test_curve_table_summarises_each_point_over_seeds():
    histories = {"a": {"r": [(0, 0.0), (10, 2.0)]}, "b": {"r": [(0, 0.0), (10, 4.0)]}}
    rows = [{"w": "1", "seed": "0", "run_id": "a"}, {"w": "1", "seed": "1", "run_id": "b"}]
    line = report.curve_table(rows, histories, "w", "r", "return").splitlines()[2]
    assert line.startswith("| 1 | 3 ± 1 |")  # final 2 and 4


def test_alpha_claims_and_the_spread_figure_from_known_rows(tmp_path):
    """Worked by hand: α = 0 lasts 1 s, α = 1e-3 3 s (3x), α = 1e-2 2 s, two seeds each (±0.1 s)."""
    from orchestrator.sweep.physicsvae import alpha_claims, plot_spread, pooled

    rows = []
    for alpha, times in ((0.0, (0.9, 1.1)), (1e-3, (2.9, 3.1)), (1e-2, (1.9, 2.1))):
        for seed, t in enumerate(times):
            rows.append({"a": alpha, "seed": seed, "m": t, "s": 0.5, "run_id": f"{alpha}-{seed}"})
    table = alpha_claims(rows, "a", key="m")
    # The ratio, on the seeds' logs: ln 2.9, ln 3.1 (mean 1.0981, variance 0.00222) against ln 0.9, ln 1.1 (mean
    # -0.0050, variance 0.02014): e^1.1031 = 3.01x; SE sqrt(0.00222/2 + 0.02014/2) = 0.1057 with Welch's 1.22
    # degrees of freedom, three statements: t(1 - 0.05/6, 1.22) = 20.8, so e^(1.1031 ± 2.202) = [0.33, 27.2]:
    # two seeds whose α = 0 values differ by 20% cannot tell 3x from 1x.
    assert (
        "α in {3e-4, 1e-3, 3e-3}: 3.00 s (2) / α = 0: 1.00 s (2) | ratio = 3.01×, 98.3% CI [0.33, 27.25]×: "
        "**not resolved**" in table
    )
    # The best range has only α = 1e-3 here; α = 1e-2 is the only other α > 0: d = +1.00 ± 1.08: not resolved.
    assert "α in {3e-4, 1e-3, 3e-3}: 3.00 s (2) vs the other α > 0: 2.00 s (2) | d = +1.00 s" in table
    assert "too large an α degrades | α = 0.01: 2.00 s (2) vs α = 0.001: 3.00 s (2) | d = -1.00 s" in table
    assert table.count("**not resolved**") == 3
    mean, std = pooled(rows[:2], "m", "s")  # rollouts of two runs: means 0.9 and 1.1, each std 0.5
    assert mean == pytest.approx(1.0) and std == pytest.approx((0.25 + 0.01) ** 0.5)
    plot_spread(rows, "a", "m", "s", "time until fall (s)", tmp_path / "spread.png", level=(2.5, "expert"))
    assert (tmp_path / "spread.png").stat().st_size > 0
