"""`+experiment=ablation_prior` at smoke size: a parent run with a child per prior and the comparison."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

ROOT = Path(__file__).resolve().parents[2]


def run_sweep(sweep_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    """The prior ablation at smoke size, four iterations a point, through the CLI."""
    command = [
        sys.executable,
        "-m",
        "orchestrator",
        "+experiment=ablation_prior",
        "scale=smoke",
        "motion=walk",
        "algo.loop.iterations=4",
    ]
    command += ["progress=false", f"hydra.sweep.dir={sweep_dir}", *overrides]
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_ablation_prior_makes_a_parent_run_with_three_children_and_a_figure(tmp_path):
    sweep_dir = tmp_path / "sweep"
    proc = run_sweep(sweep_dir)
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads((sweep_dir / "sweep.json").read_text())
    client = MlflowClient(info["uri"])
    parent = client.get_run(info["parent_run_id"])
    assert parent.info.status == "FINISHED" and parent.data.tags["sweep_id"] == parent.info.run_id
    children = client.search_runs(
        [parent.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    assert sorted(c.data.params["algo.vae.prior"] for c in children) == ["conditional", "learned", "standard_normal"]
    assert all("eval/time_until_fall_mean" in c.data.metrics for c in children)
    artifacts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"comparison.png", "comparison.md", "comparison.json"} <= artifacts
    assert "| conditional | 1 |" in (sweep_dir / "comparison.md").read_text()


@pytest.mark.slow
def test_parallel_sweep_logs_through_a_local_tracking_server(tmp_path):
    """hydra/launcher=joblib runs the points at once; they share one SQLite store through a server on 127.0.0.1."""
    sweep_dir = tmp_path / "sweep"
    proc = run_sweep(sweep_dir, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads((sweep_dir / "sweep.json").read_text())
    assert info["uri"].startswith("http://127.0.0.1:") and info["store"].startswith("sqlite:///")
    client = MlflowClient(info["store"])  # the server is gone; the store stays
    parent = client.get_run(info["parent_run_id"])
    assert parent.info.status == "FINISHED"
    children = client.search_runs(
        [parent.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    assert sorted(c.data.params["algo.vae.prior"] for c in children) == ["conditional", "learned", "standard_normal"]
    assert all(c.info.status == "FINISHED" and "eval/tracking_error_mean" in c.data.metrics for c in children)
    spans = sorted((c.info.start_time, c.info.end_time) for c in children)
    assert spans[1][0] < spans[0][1], "the first two points should have run at the same time"
    uploaded = {p.name for p in (sweep_dir / "mlartifacts").rglob("*")}
    assert {"comparison.png", "config.json"} <= uploaded  # artifacts went through the server's proxy
    assert "--artifacts-destination" in proc.stdout


@pytest.mark.slow
def test_ablation_gp_at_smoke_scale_compares_four_penalties_with_curves_and_the_paper(tmp_path):
    sweep_dir = tmp_path / "sweep"
    command = [sys.executable, "-m", "orchestrator", "+experiment=ablation_gp", "scale=smoke", "progress=false"]
    proc = subprocess.run(
        command + [f"hydra.sweep.dir={sweep_dir}"], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads((sweep_dir / "sweep.json").read_text())
    client = MlflowClient(info["uri"])
    parent = client.get_run(info["parent_run_id"])
    children = client.search_runs(
        [parent.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    assert sorted(float(c.data.params["algo.discriminator.w_gp"]) for c in children) == [0.0, 1.0, 10.0, 40.0]
    assert {c.data.params["algo.discriminator.loss"] for c in children} == {"lsgan"}
    assert {c.data.params["algo.discriminator.gp_on"] for c in children} == {"data"}
    assert all(c.data.tags["algo"] == "amp" and "eval/pose_error_dtw" in c.data.metrics for c in children)
    artifacts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"comparison.png", "curves.png", "comparison.md", "comparison.json"} <= artifacts
    table = (sweep_dir / "comparison.md").read_text()
    assert "| 40.0 | 1 |" in table and "pose error after DTW (m)" in table and "walk 0.030 m" in table
    assert "final episode return" in table  # the learning curves' summary per point
