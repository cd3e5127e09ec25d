"""The cluster's state on disk, without starting it: directories 0700 and secrets 0600 whether new or already there
(pre-created here with 0755 / 0644, as an older state dir or a umask of 022 leaves them), and the MLflow auth
config with no password in it."""

from __future__ import annotations

import configparser
import os
import shutil
import stat
from pathlib import Path

import pytest

from orchestrator.cluster import services as svc
from orchestrator.tracking import mlflow_auth
from orchestrator.tracking.secret_files import kept_dir, private_dir, read_secret, write_secret


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture(autouse=True)
def loose_umask():
    """A umask that would leave new files 0644 and directories 0755, as most shells have."""
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_private_dir_makes_new_and_existing_directories_0700(tmp_path):
    existing = tmp_path / "old"
    existing.mkdir(mode=0o755)
    existing.chmod(0o755)
    assert private_dir(existing) == existing and mode(existing) == 0o700
    new = private_dir(tmp_path / "a" / "b")
    assert mode(new) == 0o700


def test_secrets_are_0600_whether_new_or_existing(tmp_path):
    old = tmp_path / "old-secret"
    old.write_text("kept\n")
    old.chmod(0o644)
    assert read_secret(old) == "kept" and mode(old) == 0o600  # read: the mode is fixed, the value kept
    again = tmp_path / "rewritten"
    again.write_text("x")
    again.chmod(0o644)
    write_secret(again, "new")
    assert again.read_text() == "new" and mode(again) == 0o600
    made = tmp_path / "made"
    assert read_secret(made, lambda: "fresh") == "fresh" and mode(made) == 0o600
    with pytest.raises(FileNotFoundError):
        read_secret(tmp_path / "missing")


def test_write_secret_does_not_follow_a_planted_symlink(tmp_path):
    target = tmp_path / "elsewhere"
    target.write_text("untouched")
    link = tmp_path / "ray-auth-token"
    link.symlink_to(target)
    with pytest.raises(OSError):
        svc.write_token(link)
    assert target.read_text() == "untouched"


def test_the_token_the_passwords_and_the_ray_temp_dir_get_their_modes_in_an_old_state_dir(tmp_path):
    state_dir = tmp_path / "s"
    state_dir.mkdir(mode=0o755)
    state_dir.chmod(0o755)
    token = state_dir / "ray-auth-token"
    token.write_text("old")
    token.chmod(0o644)
    for name in ("mlflow-password", "mlflow-admin-password"):
        (state_dir / name).write_text(f"{name}-value\n")
        (state_dir / name).chmod(0o644)
    (state_dir / "ray").mkdir(mode=0o755)
    (state_dir / "ray").chmod(0o755)

    svc.write_token(token)
    credentials = svc.mlflow_credentials(state_dir)
    private_dir(state_dir)

    assert mode(state_dir) == 0o700
    assert mode(token) == 0o600 and len(token.read_text()) == 64  # a fresh token each up
    assert credentials["user"] == mlflow_auth.LAB_USER
    for key, name in (("password_file", "mlflow-password"), ("admin_password_file", "mlflow-admin-password")):
        assert credentials[key] == str(state_dir / name) and mode(state_dir / name) == 0o600
        assert (state_dir / name).read_text() == f"{name}-value\n"  # kept: the user database knows it
    assert svc.tracking_env(credentials) == {
        "MLFLOW_TRACKING_USERNAME": "lab",
        "MLFLOW_TRACKING_PASSWORD": "mlflow-password-value",
    }
    if len(str(state_dir / "ray")) <= svc.RAY_TEMP_MAX_CHARS:
        temp, external = svc.ray_temp_dir(state_dir)
        assert (temp, external) == (state_dir / "ray", False) and mode(temp) == 0o700


def test_new_credentials_are_random_and_0600(tmp_path):
    a = svc.mlflow_credentials(private_dir(tmp_path / "a"))
    b = svc.mlflow_credentials(private_dir(tmp_path / "b"))
    passwords = {Path(c[k]).read_text() for c in (a, b) for k in ("password_file", "admin_password_file")}
    assert len(passwords) == 4 and all(len(p) >= 32 for p in passwords)
    assert all(mode(Path(c[k])) == 0o600 for c in (a, b) for k in ("password_file", "admin_password_file"))


def test_kept_dir_is_reused_by_the_next_up_and_replaced_when_gone_or_foreign(tmp_path):
    state_dir, outside = private_dir(tmp_path / "state"), private_dir(tmp_path / "outside")
    first = kept_dir(state_dir, "postgres-home", "pg-", parent=outside)
    assert first.parent == outside and mode(first) == 0o700
    assert mode(state_dir / "postgres-home") == 0o600
    first.chmod(0o755)
    assert kept_dir(state_dir, "postgres-home", "pg-", parent=outside) == first and mode(first) == 0o700
    # A pointer to a symlink (or to a directory another user owns) is not followed: a new directory instead.
    first.rename(outside / "moved")
    first.symlink_to(outside / "moved")
    second = kept_dir(state_dir, "postgres-home", "pg-", parent=outside)
    assert second != first and second.is_dir() and not second.is_symlink()
    assert (state_dir / "postgres-home").read_text().strip() == str(second)


def test_the_auth_config_names_its_database_and_read_for_all_and_holds_no_password(tmp_path):
    path = tmp_path / "mlflow-auth.ini"
    path.write_text("stale")
    path.chmod(0o644)
    mlflow_auth.write_config(path, "postgresql+psycopg2://mlflow@127.0.0.1:5432/mlflow_auth")
    assert mode(path) == 0o600
    config = configparser.ConfigParser()
    config.read(path)
    section = dict(config["mlflow"])
    assert section["default_permission"] == "READ"  # others' runs: readable, not writable
    assert section["database_uri"] == "postgresql+psycopg2://mlflow@127.0.0.1:5432/mlflow_auth"
    assert section["admin_username"] == "admin" and "admin_password" not in section
    assert int(section["auth_cache_ttl_seconds"]) == mlflow_auth.AUTH_CACHE_S > 0  # one scrypt check a minute
    env = mlflow_auth.server_env(path, "the-admin-password")
    assert env["MLFLOW_AUTH_CONFIG_PATH"] == str(path) and env["MLFLOW_AUTH_ADMIN_PASSWORD"] == "the-admin-password"
    assert len(env["MLFLOW_FLASK_SERVER_SECRET_KEY"]) == 64
    assert "the-admin-password" not in path.read_text()


def test_a_long_state_dirs_ray_temp_dir_sits_in_a_private_directory_outside(tmp_path):
    """Ray makes its temp dir 0777; outside the state dir a 0700 directory above it keeps other users out."""
    state_dir = private_dir(tmp_path / ("long-state-dir-" * 3))
    temp, external = svc.ray_temp_dir(state_dir)
    try:
        assert external and len(str(temp)) <= svc.RAY_TEMP_MAX_CHARS and temp.is_dir()
        assert mode(temp.parent) == 0o700 and temp.parent.stat().st_uid == os.geteuid()
        assert svc.ray_temp_dir(state_dir) == (temp, True)  # the next up: the same one
    finally:
        shutil.rmtree(temp.parent)


def test_mlflow_auth_without_its_passwords_is_one_line_and_exit_1(monkeypatch, capsys):
    for key in ("MLFLOW_AUTH_ADMIN_PASSWORD", "MLFLOW_TRACKING_PASSWORD"):
        monkeypatch.delenv(key, raising=False)
    assert mlflow_auth.main(["http://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "mlflow_auth: set MLFLOW_AUTH_ADMIN_PASSWORD, MLFLOW_TRACKING_PASSWORD"
    monkeypatch.setenv("MLFLOW_AUTH_ADMIN_PASSWORD", "a")
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", "b")
    assert mlflow_auth.main(["http://127.0.0.1:9"]) == 1  # nothing listens there: one line, no traceback
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("mlflow_auth: ") and "Traceback" not in err
