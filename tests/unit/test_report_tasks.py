"""The task sweeps' reports (σ ablation, prior ablation) and the sweep's second axis, from hand-made rows."""

from __future__ import annotations

import struct
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from orchestrator.sweep import report
from orchestrator.sweep.callback import SweepCallback, child_results, claims_table
from orchestrator.sweep.tasks import (
    CLAIMS,
    FIGURES,
    plot_skill_stage,
    plot_success_style,
    prior_claims,
    sigma_claims,
    spearman,
)

SIGMA, TERRAIN = "algo.task.sigma", "terrain.kind"
PRIOR = "algo.task.skill_prior"
CONF = Path(__file__).resolve().parents[2] / "conf"

# success, style deviation (deg) per (terrain, σ), one value per seed.
SIGMA_SEEDS = {
    ("flat", "0.0"): ((0.50, 0.52), (0.0, 0.0)),
    ("flat", "0.1"): ((0.80, 0.82), (3.0, 3.2)),
    ("flat", "1.0"): ((0.80, 0.84), (20.0, 22.0)),
    ("rough", "0.0"): ((0.02, 0.04), (0.0, 0.0)),
    ("rough", "0.1"): ((0.30, 0.32), (3.5, 3.7)),
    ("rough", "1.0"): ((0.70, 0.72), (25.0, 27.0)),
}


def sigma_rows(n_seeds: int = 2) -> list[dict]:
    rows = []
    for (terrain, sigma), (success, style) in SIGMA_SEEDS.items():
        for seed in range(n_seeds):
            rows.append(
                {
                    SIGMA: sigma,
                    TERRAIN: terrain,
                    "seed": str(seed),
                    "eval/task_success": success[seed],
                    "eval/task_return": success[seed] / 2,
                    "eval/style_deviation_deg": style[seed],
                    "eval/time_until_fall_mean": 10.0 + seed,
                    "run_id": f"{terrain}-{sigma}-{seed}",
                }
            )
    return rows


def prior_rows(n_seeds: int = 3) -> list[dict]:
    # fell, return, success, time until fall (s) per prior, one value per seed.
    seeds = {
        "standard_normal": ((0.8, 0.9, 1.0), (0.20, 0.30, 0.25), (0.1, 0.0, 0.2), (3.0, 4.0, 5.0)),
        "conditional": ((0.1, 0.2, 0.0), (0.60, 0.62, 0.64), (0.7, 0.8, 0.9), (9.0, 10.0, 11.0)),
        "learned": ((0.3, 0.3, 0.3), (0.50, 0.50, 0.50), (0.5, 0.5, 0.5), (8.0, 8.0, 8.0)),
    }
    keys = ("skill/random_sampling_fell", "eval/task_return", "eval/task_success", "eval/time_until_fall_mean")
    rows = []
    for prior, values in seeds.items():
        for seed in range(n_seeds):
            row = {PRIOR: prior, "seed": str(seed), "run_id": f"{prior}-{seed}", "skill/tracking_error_mean": 0.1}
            row.update({k: v[seed] for k, v in zip(keys, values, strict=True)})
            rows.append(row)
    return rows


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) in pixels, from the PNG's IHDR chunk."""
    return struct.unpack(">II", path.read_bytes()[16:24])


def test_spearman_with_ties_and_without():
    assert spearman(np.array([1.0, 2.0, 3.0]), np.array([10.0, 30.0, 20.0])) == pytest.approx(0.5)
    # x ranks with ties (0.5, 0.5, 2.5, 2.5, 4.5, 4.5) against y ranks 0..5: 16 / sqrt(16 * 17.5) = 0.956.
    x = np.array([0.0, 0.0, 0.1, 0.1, 1.0, 1.0])
    assert spearman(x, np.arange(6.0)) == pytest.approx(16 / np.sqrt(16 * 17.5))
    assert np.isnan(spearman(np.ones(3), np.arange(3.0)))


def test_facet_by_groups_sigma_and_terrain_separately_in_the_tables():
    rows = sigma_rows()
    table = report.final_table(rows, SIGMA, {"eval/task_success": "success"}, facet_by=TERRAIN).splitlines()
    assert table[0] == "| terrain.kind | algo.task.sigma | seeds | success |"
    assert table[1] == "| --- | --- | --- | --- |"
    # Each (terrain, σ) its own row: flat σ = 0 seeds 0.50 and 0.52 -> 0.510 ± 0.010 (population std).
    assert table[2] == "| flat | 0.0 | 2 | 0.510 ± 0.010 |"
    assert table[4] == "| flat | 1.0 | 2 | 0.820 ± 0.020 |"
    assert table[5] == "| rough | 0.0 | 2 | 0.030 ± 0.010 |"
    assert len(table) == 2 + 6
    histories = {r["run_id"]: {"r": [(0, 0.0), (10, r["eval/task_success"])]} for r in rows}
    curve = report.curve_table(rows, histories, SIGMA, "r", "reward", facet_by=TERRAIN).splitlines()
    assert curve[0].startswith("| terrain.kind | algo.task.sigma | final reward |")
    assert curve[7].startswith("| rough | 1.0 | 0.71 ± 0.01 |")


def test_facet_by_none_leaves_the_old_output_unchanged():
    rows = [
        {"w": "10.0", "seed": "0", "m": 1.0, "run_id": "a"},
        {"w": "10.0", "seed": "1", "m": 3.0, "run_id": "b"},
        {"w": "2.0", "seed": "0", "m": 5.0, "run_id": "c"},
    ]
    assert report.final_table(rows, "w", {"m": "metric"}) == (
        "| w | seeds | metric |\n| --- | --- | --- |\n| 2.0 | 1 | 5.000 ± 0.000 |\n| 10.0 | 2 | 2.000 ± 1.000 |\n"
    )
    histories = {"a": {"m": [(0, 0.0), (10, 1.0)]}, "b": {"m": [(0, 0.0), (10, 3.0)]}, "c": {"m": []}}
    assert report.curve_table(rows, histories, "w", "m", "metric").splitlines()[:3] == [
        "| w | final metric | roughness | samples to half of final | samples to converge |",
        "| --- | --- | --- | --- | --- |",
        "| 2.0 | n/a | n/a | n/a | n/a |",
    ]
    assert list(report.points(rows, "w")) == [("2.0",), ("10.0",)] and list(report.group(rows, "w")) == ["2.0", "10.0"]
    # The sweep's rows: the compared parameter, the seed, the metrics and the run, in that order, no facet.
    children = [
        {"run_id": "r1", "params": {"w": "2", "seed": "1", "terrain.kind": "flat"}, "metrics": {"m": 1.0}},
        {"run_id": "r0", "params": {"w": "2", "seed": "0", "terrain.kind": "rough"}, "metrics": {}},
    ]
    plain = child_results(children, "w", ["m"])
    assert plain == [
        {"w": "2", "seed": "0", "m": None, "run_id": "r0"},
        {"w": "2", "seed": "1", "m": 1.0, "run_id": "r1"},
    ]
    faceted = child_results(children, "w", ["m"], facet_by="terrain.kind")
    assert [r["terrain.kind"] for r in faceted] == ["flat", "rough"]  # sorted by value, then facet, then seed


def test_figures_are_written_and_facets_add_a_row_of_panels(tmp_path):
    rows = sigma_rows()
    histories = {
        r["run_id"]: {"rollout/task_reward": [(0, 0.1), (100, r["eval/task_success"])], "eval/task_return": []}
        for r in rows
    }
    curves = {"rollout/task_reward": "task reward", "eval/task_return": "return"}
    report.plot_curves(rows, histories, SIGMA, curves, tmp_path / "flat.png")
    report.plot_curves(rows, histories, SIGMA, curves, tmp_path / "faceted.png", facet_by=TERRAIN)
    # 2 panels of 4.5 x 3.5 in at 100 dpi; a second terrain doubles the height.
    assert png_size(tmp_path / "flat.png") == (900, 350)
    assert png_size(tmp_path / "faceted.png") == (900, 700)
    report.plot_final(rows, SIGMA, {"eval/task_success": "success"}, tmp_path / "final.png", facet_by=TERRAIN)
    plot_success_style(rows, SIGMA, TERRAIN, tmp_path / "success_style.png")
    plot_success_style(sigma_rows(1), SIGMA, None, tmp_path / "one_seed.png")
    plot_skill_stage(prior_rows(), PRIOR, None, tmp_path / "skill_stage.png")
    for name in ("final", "success_style", "one_seed", "skill_stage"):
        assert (tmp_path / f"{name}.png").stat().st_size > 0


def test_sigma_claims_per_terrain_from_known_rows():
    table = sigma_claims(sigma_rows(), SIGMA, TERRAIN)
    lines = table.splitlines()
    flat = [line for line in lines if "| flat |" in line]
    rough = [line for line in lines if "| rough |" in line]
    assert len(flat) == 3 and len(rough) == 4  # (a), (b) on both; (e) on flat, (c) and (d) on rough
    # Five statements judged (the style statements hold by construction and are not counted): each interval
    # at 1 - 0.05/5 = 99.0%.
    assert "5 statements, Bonferroni" in table and "99.0% CI" in rough[0]
    # (a) rough: σ = 1 (0.71) against σ = 0 (0.03): +0.68, tight seeds (variance 0.0002 a side, two seeds):
    # SE = 0.01414, Welch's 2 degrees of freedom, t(0.995, 2) = 9.925: ± 0.140, so [+0.54, +0.82]: reproduced.
    assert "σ = 1 vs σ = 0: d = +0.68, 99.0% CI [+0.54, +0.82]: **reproduced**" in rough[0]
    # Over the six rough runs σ and success rank together: 16 / sqrt(16 * 17.5) = +0.96.
    assert "Spearman ρ(σ, runs) = +0.96" in rough[0]
    # (b) style: bounded by σ, so it rises with σ by construction: labelled, not judged.
    assert "σ = 0: 0°, as by construction" in rough[1]
    construction = "the helper's offset is σ·tanh(·), so the deviation is 0 at σ = 0 and at most σ"
    assert rough[1].endswith(f"holds by construction ({construction}): not judged |")
    assert "**" not in rough[1]
    assert "without the helper (σ = 0) the policy fails" in rough[2] and "mean = +0.03" in rough[2]
    assert "with the helper (σ = 1.0, Sec. 5.3) it succeeds more" in rough[3] and rough[3].endswith("**reproduced** |")
    # (e) flat: σ = 1.0 (0.82) against 0.1 (0.81) with two seeds: the interval reaches past the 0.1 margin.
    assert "σ = 1: 0.82 ± 0.02 (2)" in flat[2] and flat[2].endswith("**not resolved** |")
    assert "0.1 ≈ 5.7°" in table and "1 ≈ 57.3°" in table


def test_sigma_claims_verdicts_flip_with_the_spread_and_the_seeds():
    rows = sigma_rows()
    for r in [r for r in rows if r["seed"] == "0"]:  # a third seed on every point, 0.01 above the first
        rows.append(
            {**r, "seed": "2", "run_id": r["run_id"][:-1] + "2", "eval/task_success": r["eval/task_success"] + 0.01}
        )
    # Flat σ = 1.0 far above σ = 0.1 with tight seeds: σ = 0.1 no longer suffices.
    for r in rows:
        if r[TERRAIN] == "flat" and r[SIGMA] == "1.0":
            r["eval/task_success"] += 0.5
    flat = [line for line in sigma_claims(rows, SIGMA, TERRAIN).splitlines() if "flat ground" in line][0]
    assert flat.endswith("**contradicted** |")
    # Rough σ = 0 succeeding half the time: it does not fail.
    for r in rows:
        if r[TERRAIN] == "rough" and r[SIGMA] == "0.0":
            r["eval/task_success"] = 0.5 + 0.01 * int(r["seed"])
    fails = [line for line in sigma_claims(rows, SIGMA, TERRAIN).splitlines() if "policy fails" in line][0]
    assert fails.endswith("**contradicted** |")
    one = sigma_claims(sigma_rows(1), SIGMA, TERRAIN)
    assert one.count("fewer than two seeds on a side") == 5 and "**reproduced**" not in one
    assert "needs the terrain as the second axis" in sigma_claims(sigma_rows(), SIGMA, None)


def test_prior_claims_compare_vae_nc_with_controlvae_from_known_rows():
    table = prior_claims(prior_rows(), PRIOR)
    falls = [line for line in table.splitlines() if "falls more in random sampling" in line][0]
    # VAE-NC 0.8, 0.9, 1.0 against 0.1, 0.2, 0.0: +0.80; variances 0.01 a side, Welch df 4, four statements:
    # t(1 - 0.05/8, 4) = 4.29, so 0.80 ± 4.29 · 0.0816 = [+0.45, +1.15].
    assert "| 0.90 ± 0.08 (3) | 0.10 ± 0.08 (3) | 0.30 ± 0.00 (3) |" in falls  # learned beside them
    assert falls.endswith("d = +0.80, 98.8% CI [+0.45, +1.15]: **reproduced** |")
    fall_time = [line for line in table.splitlines() if "keeps turning and falling" in line][0]
    assert "d = -6.00 s" in fall_time and fall_time.endswith("**reproduced** |")
    assert "PULSE-style (learned; no claim here)" in table
    one = prior_claims(prior_rows(1), PRIOR)
    assert one.count("fewer than two seeds on a side") == 4


def test_the_sweep_looks_claims_up_in_both_registries_and_refuses_unknown_names():
    rows = [
        {"b": "0", "seed": "0", "eval/time_until_fall_mean": 0.5},
        {"b": "2.0", "seed": "0", "eval/time_until_fall_mean": 9.0},
    ]
    assert "β = 0: 0.50 s (1) vs β = 2: 9.00 s (1)" in claims_table("physicsvae_kl", rows, "b", None)
    assert "| flat |" in claims_table("task_sigma", sigma_rows(), SIGMA, TERRAIN)
    with pytest.raises(ValueError, match="callbacks.sweep.claims: unknown table 'task_sigmas'"):
        SweepCallback(claims="task_sigmas")
    with pytest.raises(ValueError, match="callbacks.sweep.figures: unknown"):
        SweepCallback(figures=["success-style"])
    callback = SweepCallback(compare_by=SIGMA, facet_by=TERRAIN, claims="task_sigma", figures=["success_style"])
    assert callback.facet_by == TERRAIN and callback.figures == ["success_style"]


def test_pulse_table3_claim_compares_the_full_row_with_row_one_on_pulses_rule():
    """Full PULSE at 0.90/0.92/0.94 against row 1 at 0.30/0.35/0.40 (PULSE's rule): d = +0.57, each side's
    variance 0.0004 and 0.0025 (n = 3), SE sqrt(0.0029/3) = 0.0311, Welch's df 2.6: reproduced. Our stricter
    rule is shown beside it, and two rows alike are not resolved."""
    from orchestrator.sweep.tasks import pulse_claims

    def rows(full, first):
        out = []
        for prior, values in (("learned", full), ("standard_normal", first)):
            for i, v in enumerate(values):
                out.append({"p": prior, "seed": str(i), "eval/task_success_pulse": v, "eval/task_success": v - 0.1})
        return out

    line = pulse_claims(rows([0.90, 0.92, 0.94], [0.30, 0.35, 0.40]), "p").splitlines()[2]
    assert "0.35 ± 0.04 (3) / 0.92 ± 0.02 (3) | 0.25 ± 0.04 (3) / 0.82 ± 0.02 (3)" in line
    assert "d = +0.57" in line and line.endswith("**reproduced** |")
    same = pulse_claims(rows([0.30, 0.35, 0.40], [0.31, 0.34, 0.41]), "p").splitlines()[2]
    assert "**not resolved**" in same and "would reproduce the paper's effect (0.57)" in same


@pytest.mark.parametrize("name", ["task_sigma", "prior_task", "pulse_table3"])
def test_report_presets_name_known_tables_and_figures(name):
    preset = OmegaConf.load(CONF / "report" / f"{name}.yaml")
    assert preset.claims in CLAIMS and all(f in FIGURES for f in preset.get("figures", []))
    callback = SweepCallback(compare_by=SIGMA, **OmegaConf.to_container(preset))
    assert callback.claims == name


class FakeLogger:
    """What on_multirun_end uses of the MLflow tracker, writing nothing."""

    uri, run_id = "sqlite:///unused.db", "parent"

    def __init__(self) -> None:
        self.artifacts: list[str] = []

    def flush(self) -> None:
        pass

    def log_dict(self, data: dict, name: str) -> None:
        pass

    def log_artifact(self, path: str) -> None:
        self.artifacts.append(Path(path).name)

    def close(self, status: str) -> None:
        self.status = status


def test_the_sweep_end_writes_the_faceted_comparison(tmp_path, monkeypatch):
    """on_multirun_end with the store replaced by hand-made children (no MLflow)."""
    rows = sigma_rows()
    children = [
        {
            "run_id": r["run_id"],
            "params": {SIGMA: r[SIGMA], TERRAIN: r[TERRAIN], "seed": r["seed"]},
            "metrics": {k: v for k, v in r.items() if "/" in k},
        }
        for r in rows
    ]
    curve = [(0, 0.0), (50, 0.5)]
    histories = {r["run_id"]: {"rollout/task_reward": curve, "eval/task_return": curve, "task/task": []} for r in rows}
    query = types.ModuleType("orchestrator.tracking.query")
    query.child_runs = lambda uri, parent: children
    query.metric_histories = lambda uri, ids, keys: histories
    monkeypatch.setitem(sys.modules, "orchestrator.tracking.query", query)
    preset = OmegaConf.to_container(OmegaConf.load(CONF / "report" / "task_sigma.yaml"))
    preset["curves"]["task/task"] = "no run logs this one"
    callback = SweepCallback(compare_by=SIGMA, **preset)
    callback.logger, callback.sweep_dir = FakeLogger(), tmp_path
    callback.on_multirun_end(OmegaConf.create({"preset": "ablation_sigma", "tracking": {"uri": "sqlite:///unused.db"}}))
    assert callback.logger.artifacts == ["comparison.png", "curves.png", "success_style.png", "comparison.md"]
    text = (tmp_path / "comparison.md").read_text()
    assert "| terrain.kind | algo.task.sigma | seeds | task success rate |" in text
    assert "| rough | 0.1 | 2 | 0.310 ± 0.010 |" in text
    assert "rough terrain: with the helper" in text and "Sec. 5.5.2" in text
    # The curve no run logged has no panel: two curves left, two terrains -> 2 x 2 panels.
    assert png_size(tmp_path / "curves.png") == (900, 700)
