"""A sweep whose point fails at run time (Hydra then skips `on_multirun_end`) leaves no tracking server behind
and its parent run FAILED; a parallel sweep on a `sqlite:///` store writes it through that server."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import psutil
from mlflow.tracking import MlflowClient

from orchestrator import checkpoint

ROOT = Path(__file__).resolve().parents[2]


def servers_on(port: int) -> list[psutil.Process]:
    """Processes whose command line is an MLflow server on `port` (the sweep's, found by its port)."""
    found = []
    for proc in psutil.process_iter(["cmdline"]):
        cmdline = proc.info["cmdline"] or []
        if "server" in cmdline and "--port" in cmdline and str(port) in cmdline and any("mlflow" in c for c in cmdline):
            found.append(proc)
    return found


def test_a_parallel_sweep_whose_point_fails_stops_its_server_and_fails_its_parent(tmp_path):
    """Two points at once through joblib; the second fails at run time, at its first checkpoint: a file stands
    where its checkpoints/ folder goes (nothing checks that before: it is not bad input anyone types)."""
    sweep_dir, store = tmp_path / "sweep", f"sqlite:///{tmp_path / 'store' / 'mlflow.db'}"
    (tmp_path / "store").mkdir()
    (sweep_dir / "1").mkdir(parents=True)  # the second point's run directory (run_dir: Hydra's output dir)
    (sweep_dir / "1" / "checkpoints").write_text("not a folder")
    command = [sys.executable, "-m", "orchestrator", "-m", "scale=smoke", "motion=walk", "runtime=local"]
    command += ["eval.video=false", "progress=false", "algo.loop.iterations=2", f"tracking.uri={store}"]
    command += [f"hydra.sweep.dir={sweep_dir}", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "seed=0,1"]
    proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode != 0, proc.stdout[-2000:]
    assert "FileExistsError" in proc.stderr or "NotADirectoryError" in proc.stderr, proc.stderr[-2000:]
    info = json.loads((sweep_dir / "sweep.json").read_text())
    assert info["store"] == store and info["uri"].startswith("http://127.0.0.1:")  # a server in front of SQLite
    assert servers_on(int(info["uri"].rsplit(":", 1)[1])) == []
    client = MlflowClient(store)  # the store stays whole without the server
    parent = client.get_run(info["parent_run_id"])
    assert parent.info.status == "FAILED"
    children = client.search_runs(
        [parent.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    by_seed = {c.data.params.get("seed"): c for c in children}
    assert by_seed["0"].info.status == "FINISHED" and "eval/time_until_fall_mean" in by_seed["0"].data.metrics
    # The good point's artifacts went beside the SQLite file, where a later `mlflow ui` on it finds them.
    assert list((tmp_path / "store" / "mlartifacts").rglob("config.json"))


def test_a_sequential_sweep_whose_point_fails_fails_its_parent(tmp_path):
    """The basic launcher runs the points in this process; the first fails at run time (its run directory is
    held by another command), and the sweep ends there."""
    sweep_dir = tmp_path / "sweep"
    (sweep_dir / "0").mkdir(parents=True)
    held = checkpoint.lock_run_dir(sweep_dir / "0")
    command = [sys.executable, "-m", "orchestrator", "-m", "scale=smoke", "motion=walk", "runtime=local"]
    command += ["eval.video=false", "progress=false", "algo.loop.iterations=2", f"hydra.sweep.dir={sweep_dir}"]
    command += ["seed=0,1"]
    try:
        proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    finally:
        held.close()
    assert proc.returncode != 0, proc.stdout[-2000:]
    info = json.loads((sweep_dir / "sweep.json").read_text())
    client = MlflowClient(info["store"])
    parent = client.get_run(info["parent_run_id"])
    assert parent.info.status == "FAILED" and parent.info.end_time is not None
