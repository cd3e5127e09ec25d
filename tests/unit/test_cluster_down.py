"""`cluster down` and `cluster env` on a state dir laid out as `up` leaves it, with real files and no processes (the
services have already gone, as after a reboot): down deletes no data, wherever it lives; env exports the MLflow
password from its file without printing it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from orchestrator.cluster.topology import down, save_state, state_path
from orchestrator.tracking.secret_files import kept_dir, private_dir, write_secret

ROOT = Path(__file__).resolve().parents[2]


def layout(tmp_path: Path) -> tuple[Path, dict]:
    """A state dir whose database and Ray temp dir live outside it (as `up` does as root, or for a long path):
    PostgreSQL's data directory with a table file, and a `ray job submit --working-dir .` job's run directory."""
    state_dir, outside = private_dir(tmp_path / "state"), private_dir(tmp_path / "tmp")
    pg_home = kept_dir(state_dir, "postgres-home", "mocap-pg-", parent=outside)
    (pg_home / "data" / "base" / "16384").mkdir(parents=True)
    (pg_home / "data" / "PG_VERSION").write_text("15\n")
    (pg_home / "data" / "base" / "16384" / "2619").write_bytes(b"\0" * 8192)  # a table's pages
    (pg_home / "postgres.log").write_text("database system is shut down\n")
    ray_temp = kept_dir(state_dir, "ray-temp-dir", "mocap-ray-", parent=outside)
    job = ray_temp / "session_2026-12-03_17-00-00_1_1" / "runtime_resources" / "working_dir_files" / "_ray_pkg_ab12"
    (job / "outputs" / "default" / "run").mkdir(parents=True)
    (job / "outputs" / "default" / "run" / "train.log").write_text("a job's output\n")
    private_dir(state_dir / "logs")
    write_secret(state_dir / "postgres-password", "pg-secret")
    write_secret(state_dir / "mlflow-password", "lab-secret")
    state = {
        "state_dir": str(state_dir),
        "started": 0.0,
        "ray": {
            "temp_dir": str(ray_temp),
            "temp_external": True,
            "auth_token_path": str(state_dir / "ray-auth-token"),
            "head": {"pid": 2**22 + 1, "created": 0.0, "log": "", "gcs_address": "127.0.0.1:1", "dashboard_url": ""},
            "nodes": [],
        },
        "postgres": {
            "home": str(pg_home),
            "external": True,
            "bindir": "/nonexistent/bin",  # pg_ctl is needed only while postmaster.pid exists
            "data_dir": str(pg_home / "data"),
            "log": str(pg_home / "postgres.log"),
            "password_file": str(state_dir / "postgres-password"),
        },
        "mlflow": {
            "pid": 2**22 + 2,
            "created": 0.0,
            "log": "",
            "uri": "http://127.0.0.1:5999",
            "user": "lab",
            "password_file": str(state_dir / "mlflow-password"),
            "admin_password_file": str(state_dir / "mlflow-admin-password"),
        },
    }
    save_state(state)
    return state_dir, state


def test_down_keeps_an_outside_database_and_ray_job_working_dirs(tmp_path, capsys):
    state_dir, state = layout(tmp_path)
    pg_home, ray_temp = Path(state["postgres"]["home"]), Path(state["ray"]["temp_dir"])
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())

    assert down(state_dir) is True

    assert not state_path(state_dir).exists()  # the record of running processes goes ...
    after = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    assert set(before) - {state_path(state_dir).relative_to(tmp_path)} <= set(after)  # ... and nothing else
    assert (pg_home / "data" / "base" / "16384" / "2619").stat().st_size == 8192
    assert next(ray_temp.rglob("train.log")).read_text() == "a job's output\n"
    assert (state_dir / "logs" / "postgres.log").exists()  # its log, copied beside the others
    out = capsys.readouterr().out
    assert f"kept the database in {pg_home / 'data'}" in out and f"kept the Ray temp dir in {ray_temp}" in out
    # The next up finds both again through their pointers in the state dir.
    assert kept_dir(state_dir, "postgres-home", "mocap-pg-", parent=tmp_path / "tmp") == pg_home
    assert kept_dir(state_dir, "ray-temp-dir", "mocap-ray-", parent=tmp_path / "tmp") == ray_temp


def test_env_exports_the_mlflow_user_and_reads_its_password_from_the_file_without_printing_it(tmp_path):
    state_dir, state = layout(tmp_path)
    command = [sys.executable, "-m", "orchestrator.cluster", "env", "--state-dir", str(state_dir)]
    printed = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert "lab-secret" not in printed and "MLFLOW_TRACKING_PASSWORD=" in printed
    assert "@" not in printed.split("MLFLOW_TRACKING_URI=")[1].splitlines()[0]  # no credentials in the URI
    shell = subprocess.run(
        [
            "sh",
            "-c",
            'eval "$1" && printf "%s\\n%s\\n%s" "$MLFLOW_TRACKING_URI" "$MLFLOW_TRACKING_USERNAME" '
            '"$MLFLOW_TRACKING_PASSWORD"',
            "sh",
            printed,
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    assert shell == ["http://127.0.0.1:5999", "lab", "lab-secret"]
    assert json.loads(state_path(state_dir).read_text())["mlflow"]["user"] == "lab"
