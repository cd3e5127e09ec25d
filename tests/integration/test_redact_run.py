"""A password in `tracking.uri` appears nowhere in the run: not in its params, config.json, the Hydra files it
logs, the store, the run directory's tracking files, nor stdout and stderr (a real run through the CLI, logging to
a real MLflow server on 127.0.0.1 through a URI that carries user:password)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from mlflow.tracking import MlflowClient

from orchestrator.tracking.server import start_local_server

ROOT = Path(__file__).resolve().parents[2]
PASSWORD = "Ju5tS3cretPw"


def test_a_password_in_the_tracking_uri_appears_nowhere_in_the_run(tmp_path):
    artifacts = tmp_path / "artifacts"
    with start_local_server(f"sqlite:///{tmp_path / 'server.db'}", artifacts) as server:
        uri = f"http://trainer:{PASSWORD}@127.0.0.1:{server.port}"
        run_dir = tmp_path / "run"
        command = [sys.executable, "-m", "orchestrator", "scale=smoke", "motion=walk", "runtime=local"]
        command += ["eval.video=false", "progress=false", "algo.loop.iterations=2", f"tracking.uri={uri}"]
        command += [f"hydra.run.dir={run_dir}"]
        proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        run_id = json.loads((run_dir / "run.json").read_text())["run_id"]
        client = MlflowClient(server.uri)
        run = client.get_run(run_id)
        logged = {a.path for a in client.list_artifacts(run_id, "hydra")} | {
            a.path for a in client.list_artifacts(run_id)
        }
    assert PASSWORD not in proc.stdout and PASSWORD not in proc.stderr
    assert f"MLflow: http://trainer:***@127.0.0.1:{server.port}" in proc.stderr  # where to watch, masked
    assert run.data.params["tracking.uri"] == f"http://trainer:***@127.0.0.1:{server.port}"
    assert all(PASSWORD not in v for v in [*run.data.params.values(), *run.data.tags.values()])
    assert {"config.json", "hydra/config.yaml", "hydra/overrides.yaml", "hydra/hydra.yaml"} <= logged
    stored = [p for p in artifacts.rglob("*") if p.is_file()]
    overrides = next(p for p in stored if p.name == "overrides.yaml").read_text()
    assert f"tracking.uri=http://trainer:***@127.0.0.1:{server.port}" in overrides
    # Every file the store holds, the database included, and every file of the run directory, Hydra's record of
    # the command line (.hydra/) included: it is rewritten with the password masked.
    files = stored + [tmp_path / "server.db"]
    files += [p for p in run_dir.rglob("*") if p.is_file()]
    assert (run_dir / ".hydra" / "overrides.yaml").exists()
    leaks = [p for p in files if PASSWORD.encode() in p.read_bytes()]
    assert leaks == []


def test_a_sweep_keeps_the_password_only_in_its_own_0600_file(tmp_path):
    """A sweep's points read the store from sweep.json (0600, this user's); Hydra's multirun.yaml and every
    point's record are masked, and nothing logged holds the password."""
    artifacts = tmp_path / "artifacts"
    with start_local_server(f"sqlite:///{tmp_path / 'server.db'}", artifacts) as server:
        uri = f"http://trainer:{PASSWORD}@127.0.0.1:{server.port}"
        sweep_dir = tmp_path / "sweep"
        command = [sys.executable, "-m", "orchestrator", "-m", "scale=smoke", "motion=walk", "runtime=local"]
        command += ["eval.video=false", "progress=false", "algo.loop.iterations=2", f"tracking.uri={uri}", "seed=0"]
        command += [f"hydra.sweep.dir={sweep_dir}"]
        proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
    assert PASSWORD not in proc.stdout and PASSWORD not in proc.stderr
    sweep_file = sweep_dir / "sweep.json"
    assert oct(sweep_file.stat().st_mode & 0o777) == "0o600" and PASSWORD in sweep_file.read_text()
    assert (sweep_dir / "multirun.yaml").exists() and (sweep_dir / "0" / ".hydra" / "overrides.yaml").exists()
    files = [p for p in [*sweep_dir.rglob("*"), *artifacts.rglob("*"), tmp_path / "server.db"] if p.is_file()]
    leaks = [p for p in files if p != sweep_file and PASSWORD.encode() in p.read_bytes()]
    assert leaks == []
