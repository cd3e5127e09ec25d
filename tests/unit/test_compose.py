"""docker/compose.yaml: the services, commands and ports that docs/cluster.md and the cluster path rely on.

No Docker daemon runs here, so the file is checked as data; `docker compose config` (or the older
`docker-compose config`) also validates it where a Compose client is installed.
"""

from __future__ import annotations

import configparser
import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker" / "compose.yaml"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def option(command: list[str], name: str) -> str:
    """The value after `name` in a command list."""
    assert name in command, f"{name} missing from {command}"
    return command[command.index(name) + 1]


SECRETS = {"RAY_AUTH_TOKEN", "MLFLOW_DB_PASSWORD", "MLFLOW_ADMIN_PASSWORD", "MLFLOW_TRACKING_PASSWORD"}
SECRETS |= {"MLFLOW_FLASK_SECRET_KEY"}


def mounted(service: dict, target: str) -> Path:
    """The file of this repository that `service` mounts at `target` (read-only)."""
    for volume in service["volumes"]:
        source, _, rest = volume.partition(":")
        if rest.split(":")[0] == target:
            assert rest.endswith(":ro"), volume
            return (COMPOSE.parent / source).resolve()
    raise AssertionError(f"nothing mounted at {target}: {service['volumes']}")


def test_the_services_are_a_ray_head_workers_mlflow_its_user_and_postgres(compose):
    assert set(compose["services"]) == {"ray-head", "ray-worker", "mlflow", "mlflow-user", "postgres"}
    assert compose["services"]["postgres"]["image"].startswith("postgres:")
    for name in ("ray-head", "ray-worker", "mlflow", "mlflow-user"):  # the project's image, from docker/Dockerfile
        build = compose["services"][name]["build"]
        assert (COMPOSE.parent / build["context"] / build["dockerfile"]).resolve() == ROOT / "docker" / "Dockerfile"
        assert compose["services"][name]["image"] == "mocap-orchestrator:latest"


def test_ray_workers_join_the_head_with_token_authentication(compose):
    head, worker = compose["services"]["ray-head"], compose["services"]["ray-worker"]
    assert head["command"][:4] == ["ray", "start", "--head", "--block"]
    assert option(worker["command"], "--address") == f"ray-head:{option(head['command'], '--port')}"
    assert "--block" in worker["command"] and "--num-cpus" in worker["command"]
    assert str(worker["deploy"]["replicas"]).startswith("${RAY_WORKERS:-")  # scalable: RAY_WORKERS or --scale
    for service in (head, worker):
        assert service["environment"]["RAY_AUTH_MODE"] == "token"
        assert service["environment"]["RAY_AUTH_TOKEN"].startswith("${RAY_AUTH_TOKEN:?")  # required, no default
        assert service["shm_size"]
    assert worker["depends_on"]["ray-head"]["condition"] == "service_healthy"


def test_only_the_dashboard_and_mlflow_are_published_and_only_on_loopback(compose):
    published = {name: s.get("ports", []) for name, s in compose["services"].items()}
    dashboard = option(compose["services"]["ray-head"]["command"], "--dashboard-port")
    mlflow_port = option(compose["services"]["mlflow"]["command"], "--port")
    assert published == {
        "ray-head": [f"127.0.0.1:{dashboard}:{dashboard}"],
        "ray-worker": [],
        "mlflow": [f"127.0.0.1:{mlflow_port}:{mlflow_port}"],
        "mlflow-user": [],
        "postgres": [],
    }
    assert not any("expose" in s or s.get("network_mode") == "host" for s in compose["services"].values())


def test_mlflow_runs_the_basic_auth_app_with_read_for_all_and_no_password_in_its_config(compose):
    mlflow = compose["services"]["mlflow"]
    assert option(mlflow["command"], "--app-name") == "basic-auth"
    config_path = mounted(mlflow, mlflow["environment"]["MLFLOW_AUTH_CONFIG_PATH"])
    assert config_path.parent == ROOT / "docker"
    config = configparser.ConfigParser()
    config.read(config_path)
    auth = dict(config["mlflow"])
    assert auth["default_permission"] == "READ"  # an authenticated user cannot write to another's runs
    assert auth["database_uri"] == "postgresql+psycopg2://mlflow@postgres:5432/mlflow_auth"
    assert "admin_password" not in auth and auth["admin_username"] == "admin"
    assert int(auth["auth_cache_ttl_seconds"]) > 0  # a checked password is remembered (scrypt per request is slow)
    # The admin's password and Flask's CSRF key: from the environment, required (no default, hence no known one).
    assert mlflow["environment"]["MLFLOW_AUTH_ADMIN_PASSWORD"].startswith("${MLFLOW_ADMIN_PASSWORD:?")
    assert mlflow["environment"]["MLFLOW_FLASK_SERVER_SECRET_KEY"].startswith("${MLFLOW_FLASK_SECRET_KEY:?")
    # The auth app's database exists: the postgres image runs this script on an empty volume.
    init = mounted(compose["services"]["postgres"], "/docker-entrypoint-initdb.d/10-mlflow-auth.sql")
    assert "CREATE DATABASE mlflow_auth;" in init.read_text()


def test_jobs_log_as_the_lab_user_that_mlflow_user_creates_before_ray_starts(compose):
    services = compose["services"]
    user = services["mlflow-user"]
    assert user["command"][:3] == ["python", "-m", "orchestrator.tracking.mlflow_auth"]
    assert user["depends_on"]["mlflow"]["condition"] == "service_healthy"
    assert services["ray-head"]["depends_on"]["mlflow-user"]["condition"] == "service_completed_successfully"
    for name in ("ray-head", "ray-worker", "mlflow-user"):
        env = services[name]["environment"]
        assert env["MLFLOW_TRACKING_USERNAME"] == user["environment"]["MLFLOW_TRACKING_USERNAME"]
        assert env["MLFLOW_TRACKING_PASSWORD"].startswith("${MLFLOW_TRACKING_PASSWORD:?")
    assert (
        user["environment"]["MLFLOW_AUTH_ADMIN_PASSWORD"]
        == services["mlflow"]["environment"]["MLFLOW_AUTH_ADMIN_PASSWORD"]
    )


def test_no_secret_is_written_in_the_file_or_in_a_uri(compose):
    for name, service in compose["services"].items():
        for key, value in (service.get("environment") or {}).items():
            if re.search("PASSWORD|TOKEN|SECRET", key):
                variable = re.fullmatch(r"\$\{(\w+):\?[^}]*\}", str(value))
                assert variable and variable.group(1) in SECRETS, f"{name}.{key}: {value}"
        for arg in service.get("command") or []:
            assert not re.search(r"://[^/@\s]*:[^/@\s]*@", str(arg)), f"{name}: credentials in {arg}"


def test_mlflow_serves_postgres_runs_and_proxies_artifacts_into_a_volume(compose):
    mlflow, postgres = compose["services"]["mlflow"], compose["services"]["postgres"]
    command = mlflow["command"]
    assert command[:2] == ["mlflow", "server"]
    user, db = postgres["environment"]["POSTGRES_USER"], postgres["environment"]["POSTGRES_DB"]
    # psycopg2 named: SQLAlchemy 2.1 maps a bare postgresql:// to psycopg 3, which the project does not install.
    assert option(command, "--backend-store-uri") == f"postgresql+psycopg2://{user}@postgres:5432/{db}"
    assert mlflow["environment"]["PGPASSWORD"] == postgres["environment"]["POSTGRES_PASSWORD"]
    destination = option(command, "--artifacts-destination")
    assert f"mlartifacts:{destination}" in mlflow["volumes"] and "mlartifacts" in compose["volumes"]
    assert "--default-artifact-root" not in command and "--no-serve-artifacts" not in command  # proxied
    assert "mlflow" in option(command, "--allowed-hosts").split(",")  # jobs reach it as http://mlflow:5000
    assert any(v.startswith("pgdata:") for v in postgres["volumes"])
    assert mlflow["depends_on"]["postgres"]["condition"] == "service_healthy"


def test_the_image_installs_the_project_with_its_postgres_driver():
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    assert "-e ." in dockerfile and "COPY conf conf" in dockerfile
    dependencies = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(d.startswith("psycopg2") for d in dependencies)
    assert any(d.startswith("mlflow[auth]") for d in dependencies)  # Flask-WTF, which the basic-auth app imports
    assert any(d.startswith("ray[default]") for d in dependencies)  # the dashboard and jobs API


def compose_client() -> list[str] | None:
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0:
        return [docker, "compose"]
    return [shutil.which("docker-compose")] if shutil.which("docker-compose") else None


def test_compose_config_accepts_the_file():
    client = compose_client()
    if client is None:
        pytest.skip("no Compose client (docker compose or docker-compose) installed")
    env = dict(os.environ, RAY_AUTH_TOKEN="0" * 64, MLFLOW_DB_PASSWORD="x", MLFLOW_ADMIN_PASSWORD="a")
    env.update(MLFLOW_TRACKING_PASSWORD="b", MLFLOW_FLASK_SECRET_KEY="c")
    proc = subprocess.run([*client, "-f", str(COMPOSE), "config"], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "ray-worker" in proc.stdout
    missing = {k: v for k, v in env.items() if k != "RAY_AUTH_TOKEN"}
    proc = subprocess.run([*client, "-f", str(COMPOSE), "config"], capture_output=True, text=True, env=missing)
    assert proc.returncode != 0 and "RAY_AUTH_TOKEN" in proc.stderr  # no cluster without a token
    missing = {k: v for k, v in env.items() if k != "MLFLOW_ADMIN_PASSWORD"}
    proc = subprocess.run([*client, "-f", str(COMPOSE), "config"], capture_output=True, text=True, env=missing)
    assert proc.returncode != 0 and "MLFLOW_ADMIN_PASSWORD" in proc.stderr  # nor without the admin's password
