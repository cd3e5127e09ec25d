"""A run aimed at an MLflow server that asks for a user (MLflow's basic-auth app, as `make cluster-up` runs it) is
refused with one line before anything starts when this process has no credentials or wrong ones, instead of
spooling every record for ever; with the right ones it goes ahead."""

from __future__ import annotations

import os
import sys
import time

import pytest
from test_bad_input import assert_refused, run_main  # beside this file (pytest puts its folder on sys.path)

from orchestrator import preflight
from orchestrator.cluster.procs import free_port, http_ok, start_session, stop_session
from orchestrator.preflight import InputError
from orchestrator.tracking import mlflow_auth

pytestmark = pytest.mark.slow
PASSWORD = "an-admin-password-for-this-test"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """`mlflow server --app-name basic-auth` on SQLite, on a free port of 127.0.0.1."""
    mlflow_auth.require_auth_app()
    root = tmp_path_factory.mktemp("auth-server")
    config = root / "auth.ini"
    mlflow_auth.write_config(config, f"sqlite:///{root / 'users.db'}")
    port = free_port()
    command = [sys.executable, "-m", "mlflow", "server", "--app-name", "basic-auth", "--workers", "1"]
    command += ["--backend-store-uri", f"sqlite:///{root / 'mlflow.db'}", "--host", "127.0.0.1", "--port", str(port)]
    command += ["--artifacts-destination", str(root / "artifacts")]
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_TRACKING_")}
    record = start_session(command, root / "server.log", {**env, **mlflow_auth.server_env(config, PASSWORD)})
    uri = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while not http_ok(f"{uri}/health"):
            assert time.monotonic() < deadline, (root / "server.log").read_text()[-2000:]
            time.sleep(0.5)
        yield uri
    finally:
        stop_session(record)


def test_no_credentials_or_wrong_ones_are_refused_in_one_line(server, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_USERNAME", raising=False)
    monkeypatch.delenv("MLFLOW_TRACKING_PASSWORD", raising=False)
    with pytest.raises(InputError, match=rf"tracking.uri={server}: the server asks for a user: set MLFLOW_TRACKING_"):
        preflight.tracking_server(server)
    monkeypatch.setenv("MLFLOW_TRACKING_USERNAME", mlflow_auth.ADMIN_USER)
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", "not-the-password")
    with pytest.raises(InputError, match=r"the server refuses user 'admin' \(401\); check MLFLOW_TRACKING_PASSWORD"):
        preflight.tracking_server(server)
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", PASSWORD)
    preflight.tracking_server(server)  # accepted


def test_the_command_without_credentials_stops_before_anything_starts(server, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_USERNAME", raising=False)
    monkeypatch.delenv("MLFLOW_TRACKING_PASSWORD", raising=False)
    code, err = run_main(tmp_path, capsys, "motion=walk", f"tracking.uri={server}")
    line = assert_refused(tmp_path, code, err, f"tracking.uri={server}", "MLFLOW_TRACKING_USERNAME")
    assert line.startswith("error: ") and "Traceback" not in err
    assert not (tmp_path / "run").exists()


def test_a_server_that_does_not_answer_is_left_to_the_tracker():
    preflight.tracking_server(f"http://127.0.0.1:{free_port()}")  # nothing listens: the tracker will spool
