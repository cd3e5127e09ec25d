"""The MLflow tracker against a real local tracking server: a server that is down at first, then
started on the same port, receives everything the tracker spooled; parallel writers share it."""

from __future__ import annotations

import threading
import time

import pytest
from mlflow.tracking import MlflowClient

from orchestrator.tracking.mlflow import SPOOL_FILE, MlflowLogger
from orchestrator.tracking.server import ServerStartError, free_port, start_local_server

pytestmark = pytest.mark.slow  # each server takes a few seconds to start


def test_spooled_records_reach_a_server_started_later(tmp_path):
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    run_dir = tmp_path / "run"
    start = time.perf_counter()
    tags = {"sweep_id": "s1"}
    # A long retry interval: after the forced flush succeeds, nothing may wait for it to pass.
    tracker = MlflowLogger(uri, "ablation_alpha", "alpha=3e-4", tags=tags, run_dir=run_dir, retry_interval_s=60)
    tracker.log_params({"algo.alpha": "0.0003"})
    for step in range(0, 5000, 1000):
        tracker.log_metrics({"vae/loss": step / 1000, "throughput/sps": 100.0}, step=step)
    tracker.log_dict({"algo": {"alpha": 3e-4}}, "config.json")
    assert time.perf_counter() - start < 10  # seconds, not MLflow's default minutes of retries
    assert tracker.run_id is None
    assert tracker.pending() == 1 + 1 + 5 + 1
    assert (run_dir / SPOOL_FILE).exists()

    with start_local_server(f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "artifacts", port=port) as server:
        assert server.uri == uri
        tracker.flush()
        assert tracker.pending() == 0 and not (run_dir / SPOOL_FILE).exists()
        assert tracker.run_id is not None
        tracker.log_metrics({"vae/loss": 5.0}, step=5000)  # sent directly now
        tracker.close()

        client = MlflowClient(server.uri)
        run = client.get_run(tracker.run_id)
        assert run.info.run_name == "alpha=3e-4" and run.info.status == "FINISHED"
        assert run.data.tags["sweep_id"] == "s1" and run.data.params == {"algo.alpha": "0.0003"}
        steps = [(m.step, m.value) for m in client.get_metric_history(tracker.run_id, "vae/loss")]
        assert sorted(steps) == [(s * 1000, float(s)) for s in range(6)]
        assert {a.path for a in client.list_artifacts(tracker.run_id)} == {"artifacts.sha256.json", "config.json"}
        assert run.data.tags["artifacts_sha256"]  # complete: the spooled upload landed before the tag
    assert not server.running()


def test_parallel_trackers_share_one_server(tmp_path):
    with start_local_server(f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "artifacts") as server:
        parent = MlflowLogger(server.uri, "ablation_gp", run_name="sweep", run_dir=tmp_path / "parent")

        def child(i: int) -> None:
            tracker = MlflowLogger(
                server.uri, "ablation_gp", run_name=f"w_gp={i}", parent_run_id=parent.run_id, run_dir=tmp_path / f"c{i}"
            )
            for step in range(20):
                tracker.log_metrics({"disc/loss": float(step), "ppo/return": float(i)}, step=step)
            tracker.close()
            assert tracker.pending() == 0

        threads = [threading.Thread(target=child, args=(i,)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        parent.close()

        client = MlflowClient(server.uri)
        experiment = client.get_experiment_by_name("ablation_gp")
        children = client.search_runs([experiment.experiment_id], f"tags.mlflow.parentRunId = '{parent.run_id}'")
        assert sorted(r.info.run_name for r in children) == [f"w_gp={i}" for i in range(4)]
        for run in children:
            assert len(client.get_metric_history(run.info.run_id, "disc/loss")) == 20


def test_a_server_that_cannot_start_says_why(tmp_path):
    with pytest.raises(ServerStartError, match="exited") as info:
        start_local_server("notadb://nowhere", tmp_path / "artifacts", timeout=30)
    assert "log" in str(info.value)


def test_the_sweeps_server_asks_for_its_password_and_removes_its_users_at_stop(tmp_path, monkeypatch):
    """auth=True (a parallel sweep's server): a request without the password is refused (401), one with
    `server.credentials` is served, and the users' database goes with the server."""
    import urllib.error
    import urllib.request

    with start_local_server(f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "artifacts", auth=True) as server:
        assert server.private is not None and oct(server.private.stat().st_mode & 0o777) == "0o700"
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"{server.uri}/api/2.0/mlflow/experiments/search?max_results=1", timeout=10)
        assert refused.value.code == 401
        for key, value in server.credentials.items():
            monkeypatch.setenv(key, value)
        experiment = MlflowClient(server.uri).create_experiment("with-auth")
        assert MlflowClient(server.uri).get_experiment(experiment).name == "with-auth"
    assert not server.running() and not server.private.exists()


def test_a_server_outlives_no_process_that_started_it_even_one_killed_outright(tmp_path):
    """A sweep killed by SIGKILL runs no cleanup: its server (started from the main thread) goes with it."""
    import signal
    import subprocess
    import sys

    import psutil

    script = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from orchestrator.tracking.server import start_local_server\n"
        f"server = start_local_server('sqlite:///{tmp_path / 'server.db'}', Path({str(tmp_path / 'a')!r}))\n"
        "print(server.process.pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        server_pid = int(parent.stdout.readline())
        assert psutil.pid_exists(server_pid)
        parent.send_signal(signal.SIGKILL)
        parent.wait(30)
        gone, _ = psutil.wait_procs([psutil.Process(server_pid)], timeout=30)
        assert gone, "the server outlived the process that started it"
    finally:
        parent.kill()
