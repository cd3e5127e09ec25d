"""Sweep presets at smoke size: a parent run with a child per point and the comparison (prior, sigma, gp)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from mlflow.tracking import MlflowClient

ROOT = Path(__file__).resolve().parents[2]


def run_preset(sweep_dir: Path, preset: str, *overrides: str) -> subprocess.CompletedProcess:
    """`+experiment=<preset> scale=smoke` through the CLI, into `sweep_dir`; it must succeed."""
    command = [sys.executable, "-m", "orchestrator", f"+experiment={preset}", "scale=smoke", "progress=false"]
    command += ["runtime=local", "eval.video=false", f"hydra.sweep.dir={sweep_dir}", *overrides]
    proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def run_sweep(sweep_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    """The prior ablation at smoke size, four iterations a point, through the CLI."""
    return run_preset(sweep_dir, "ablation_prior", "motion=walk", "algo.loop.iterations=4", *overrides)


def parent_and_children(sweep_dir: Path, store: str = "uri") -> tuple[MlflowClient, Any, list]:
    """The sweep's MLflow client (on sweep.json's `uri` or `store`), its parent run and the parent's children."""
    info = json.loads((sweep_dir / "sweep.json").read_text())
    client = MlflowClient(info[store])
    parent = client.get_run(info["parent_run_id"])
    children = client.search_runs(
        [parent.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    return client, parent, children


@pytest.mark.slow
def test_ablation_prior_makes_a_parent_run_with_three_children_and_a_figure(tmp_path):
    sweep_dir = tmp_path / "sweep"
    run_sweep(sweep_dir)
    client, parent, children = parent_and_children(sweep_dir)
    assert parent.info.status == "FINISHED" and parent.data.tags["sweep_id"] == parent.info.run_id
    # Each point is a heading task on its own skill stage (that prior, that seed), whose evaluation it carries.
    priors = ["conditional", "learned", "standard_normal"]
    assert sorted(c.data.params["algo.task.skill_prior"] for c in children) == priors
    assert all({"eval/task_return", "skill/random_sampling_fell"} <= c.data.metrics.keys() for c in children)
    skills = {c.data.tags["upstream.skill"] for c in children}
    assert len(skills) == 3
    assert sorted(client.get_run(r).data.params["algo.vae.prior"] for r in skills) == priors
    nc = next(client.get_run(r) for r in skills if client.get_run(r).data.params["algo.vae.prior"] == "standard_normal")
    assert nc.data.params["algo.vae.posterior_std"] == "1.0"  # VAE-NC
    artifacts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"comparison.png", "comparison.md", "comparison.json", "curves.png", "skill_stage.png"} <= artifacts
    text = (sweep_dir / "comparison.md").read_text()
    assert "| conditional | 1 |" in text and "VAE-NC falls more in random sampling" in text


@pytest.mark.slow
def test_parallel_sweep_logs_through_a_local_tracking_server(tmp_path):
    """hydra/launcher=joblib runs the points at once; they share one SQLite store through a server on 127.0.0.1."""
    sweep_dir = tmp_path / "sweep"
    proc = run_sweep(sweep_dir, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    info = json.loads((sweep_dir / "sweep.json").read_text())
    assert info["uri"].startswith("http://127.0.0.1:") and info["store"].startswith("sqlite:///")
    client, parent, children = parent_and_children(sweep_dir, "store")  # the server is gone; the store stays
    assert parent.info.status == "FINISHED"
    priors = ["conditional", "learned", "standard_normal"]
    assert sorted(c.data.params["algo.task.skill_prior"] for c in children) == priors
    assert all(c.info.status == "FINISHED" and "skill/tracking_error_mean" in c.data.metrics for c in children)
    # Each point trains its skill stage, then its task: runs of two points (a stage or a task) overlap in time.
    runs = [r for r in client.search_runs([parent.info.experiment_id]) if r.info.run_id != parent.info.run_id]
    spans = sorted((r.info.start_time, r.info.end_time) for r in runs)
    overlaps = [b[0] < a[1] for a, b in zip(spans, spans[1:], strict=False)]
    assert any(overlaps), "two points should have run at the same time"
    uploaded = {p.name for p in (sweep_dir / "mlartifacts").rglob("*")}
    assert {"comparison.png", "config.json"} <= uploaded  # artifacts went through the server's proxy
    assert "--artifacts-destination" in proc.stdout


@pytest.mark.slow
def test_ablation_gp_at_smoke_scale_compares_four_penalties_with_curves_and_the_paper(tmp_path):
    sweep_dir = tmp_path / "sweep"
    run_preset(sweep_dir, "ablation_gp")
    client, parent, children = parent_and_children(sweep_dir)
    assert sorted(float(c.data.params["algo.discriminator.w_gp"]) for c in children) == [0.0, 1.0, 10.0, 40.0]
    assert {c.data.params["algo.discriminator.loss"] for c in children} == {"lsgan"}
    assert {c.data.params["algo.discriminator.gp_on"] for c in children} == {"data"}
    assert all(c.data.tags["algo"] == "amp" and "eval/pose_error_dtw" in c.data.metrics for c in children)
    artifacts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"comparison.png", "curves.png", "comparison.md", "comparison.json"} <= artifacts
    table = (sweep_dir / "comparison.md").read_text()
    assert "| 40.0 | 1 |" in table and "pose error after DTW, Eq. 10 as written" in table and "walk 0.030 m" in table
    assert "final episode return" in table  # the learning curves' summary per point


@pytest.mark.slow
def test_ablation_sigma_at_smoke_scale_shares_one_skill_stage_and_plots_success_against_style(tmp_path):
    sweep_dir = tmp_path / "sweep"
    run_preset(sweep_dir, "ablation_sigma")
    client, parent, children = parent_and_children(sweep_dir)
    points = sorted((c.data.params["terrain.kind"], float(c.data.params["algo.task.sigma"])) for c in children)
    assert points == [(t, s) for t in ("flat", "rough") for s in (0.0, 0.1, 0.5, 1.0)]
    assert len({c.data.tags["upstream.skill"] for c in children}) == 1  # one skill stage for every point
    for c in children:  # the helper's deviation is bounded by sigma, and zero without it
        sigma, style = float(c.data.params["algo.task.sigma"]), c.data.metrics["eval/style_deviation_deg"]
        assert style == 0.0 if sigma == 0 else 0.0 < style <= math.degrees(sigma)
    artifacts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"comparison.md", "success_style.png", "curves.png"} <= artifacts
    text = (sweep_dir / "comparison.md").read_text()
    assert "| rough | 1.0 | 1 |" in text and "rough terrain: with the helper" in text


@pytest.mark.slow
def test_ablation_prior_pulse_runs_table3s_first_and_last_rows_as_configurations(tmp_path):
    sweep_dir = tmp_path / "sweep"
    run_preset(sweep_dir, "ablation_prior_pulse")
    client, parent, children = parent_and_children(sweep_dir)
    rows = {}
    for c in children:
        skill = client.get_run(c.data.tags["upstream.skill"]).data.params
        rows[c.data.params["algo.task.skill_prior"]] = (
            skill["algo.vae.prior"],
            skill["algo.pulse.prior_action"],
            float(skill["algo.vae.lambda_regu"]),
        )
        assert c.data.params["algo.task.task"] == "vr" and "eval/task_success" in c.data.metrics
    assert rows == {"standard_normal": ("standard_normal", "False", 0.0), "learned": ("learned", "True", 0.005)}
    assert "93.4 %" in (sweep_dir / "comparison.md").read_text()


def test_a_point_with_bad_input_ends_the_sweep_with_one_line_and_its_parent_failed(tmp_path):
    """The first point's w_gp is negative: it is refused with the key named, exit 2, and the sweep's
    parent run is closed as FAILED rather than left RUNNING (the multirun ends at that point)."""
    sweep_dir = tmp_path / "sweep"
    command = [sys.executable, "-m", "orchestrator", "+experiment=ablation_gp", "scale=smoke", "progress=false"]
    command += ["runtime=local", f"hydra.sweep.dir={sweep_dir}", "algo.discriminator.w_gp=-1,0"]
    proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("config error:") and "w_gp" in last and "Traceback" not in proc.stderr
    _, parent, children = parent_and_children(sweep_dir)
    assert parent.info.status == "FAILED" and children == []
