"""docker/compose.yaml: the services, commands and ports that docs/cluster.md and the cluster path rely on.

No Docker daemon runs here, so the file is checked as data; `docker compose config` (or the older
`docker-compose config`) also validates it where a Compose client is installed.
"""

from __future__ import annotations

import os
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


def test_the_services_are_a_ray_head_workers_mlflow_and_postgres(compose):
    assert set(compose["services"]) == {"ray-head", "ray-worker", "mlflow", "postgres"}
    assert compose["services"]["postgres"]["image"].startswith("postgres:")
    for name in ("ray-head", "ray-worker", "mlflow"):  # the project's image, built from docker/Dockerfile
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
        "postgres": [],
    }


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
    env = dict(os.environ, RAY_AUTH_TOKEN="0" * 64, MLFLOW_DB_PASSWORD="x")
    proc = subprocess.run([*client, "-f", str(COMPOSE), "config"], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "ray-worker" in proc.stdout
    missing = {k: v for k, v in env.items() if k != "RAY_AUTH_TOKEN"}
    proc = subprocess.run([*client, "-f", str(COMPOSE), "config"], capture_output=True, text=True, env=missing)
    assert proc.returncode != 0 and "RAY_AUTH_TOKEN" in proc.stderr  # no cluster without a token
