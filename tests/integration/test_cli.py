"""`python -m orchestrator` as users run it: a bad value refused before anything starts, and a run
killed after a checkpoint that resumes into the same MLflow run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

ROOT = Path(__file__).resolve().parents[2]


def orchestrator(*args: str, cwd: Path = ROOT, **kwargs) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "orchestrator", "runtime=local", "eval.video=false", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


def test_a_run_writes_only_into_the_run_dir_it_is_given_and_a_refused_one_nowhere(tmp_path):
    """Hydra's own record (.hydra/, its log) goes into `run_dir=`, not into outputs/ of the working directory; a
    command refused before it starts leaves nothing behind, there or in outputs/."""
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    args = ["scale=smoke", "motion=walk", "tracking=off", "progress=false", "algo.loop.iterations=1"]
    proc = orchestrator(*args, f"run_dir={tmp_path / 'run'}", cwd=cwd)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-2000:]
    assert list(cwd.iterdir()) == []
    assert "run_dir=" in (tmp_path / "run" / ".hydra" / "overrides.yaml").read_text()
    assert (tmp_path / "run" / "checkpoints" / "ckpt-0000001.pt").exists()
    for refused in (["seed=-1"], ["seed=-1", f"run_dir={tmp_path / 'new'}"]):
        proc = orchestrator(*args, *refused, cwd=cwd)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2 and err.strip().startswith("config error: seed: -1"), err[-2000:]
    assert list(cwd.iterdir()) == [] and not (tmp_path / "new").exists()


def test_bad_value_fails_before_anything_starts(tmp_path):
    proc = orchestrator("scale=smoke", "motion=walk", f"run_dir={tmp_path / 'bad'}", "algo.vae.prior=uniform")
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 2
    assert "config error: algo.vae.prior: unknown prior type 'uniform'" in err
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_killed_run_resumes_into_the_same_mlflow_run(tmp_path):
    run_dir = tmp_path / "run"
    common = ["scale=smoke", "motion=walk", f"run_dir={run_dir}", "progress=false", "algo.loop.checkpoint_every=2"]
    proc = orchestrator(*common, "algo.loop.iterations=1000")
    ckpt_dir = run_dir / "checkpoints"
    deadline = time.time() + 240
    while time.time() < deadline and not list(ckpt_dir.glob("ckpt-0000004.pt")):
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    last = max(int(p.stem.split("-")[1]) for p in ckpt_dir.glob("ckpt-*.pt"))
    run_id = json.loads((run_dir / "run.json").read_text())["run_id"]

    resumed = orchestrator(*common, f"algo.loop.iterations={last + 4}", "resume=true")
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err[-3000:]
    assert "resumed from" in err and "MLflow UI: mlflow ui --backend-store-uri" in out
    assert json.loads((run_dir / "run.json").read_text())["run_id"] == run_id
    client = MlflowClient(f"sqlite:///{run_dir}/mlflow.db")
    assert client.get_run(run_id).info.status == "FINISHED"
    steps = [m.step for m in client.get_metric_history(run_id, "throughput/samples_per_s")]
    per_iteration = 2 * 8 * 16
    # Logged before the kill (possibly past the checkpoint) and after: the resumed steps continue from it.
    assert steps[-4:] == [per_iteration * i for i in range(last + 1, last + 5)]
    assert len(client.search_runs([client.get_run(run_id).info.experiment_id])) == 1
    # Named by what it is, with Hydra's own record of the config and overrides beside config.json.
    name = client.get_run(run_id).info.run_name
    assert name.startswith("controlvae seed=0 runtime=local eval.video=false scale=smoke motion=walk"), name
    hydra = {a.path for a in client.list_artifacts(run_id, "hydra")}
    assert {"hydra/config.yaml", "hydra/overrides.yaml", "hydra/hydra.yaml"} <= hydra
