"""The services of `orchestrator.cluster`: Ray nodes, PostgreSQL and the MLflow server, each started and stopped.

Each `start_*` returns the service's record (addresses, pid, log) for `<state-dir>/cluster.json`
and returns only once the service answers; each `stop_*` stops what its record names, nothing else.
"""

from __future__ import annotations

import glob
import os
import pwd
import secrets
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from orchestrator.cluster.procs import (
    ServiceError,
    free_ports,
    http_json,
    http_ok,
    start_session,
    stop_session,
    wait_until,
)
from orchestrator.tracking import mlflow_auth
from orchestrator.tracking.secret_files import kept_dir, new_password, private_dir, read_secret, write_secret

HOST = "127.0.0.1"
PG_USER = "mlflow"  # the database role, and the database is `mlflow`
PG_OS_USER = "postgres"  # PostgreSQL refuses to run as root: as root, its commands run as this user
# Ray's unix sockets live under <temp-dir>/session_<date>_<pid>/sockets/ and a socket path has 107 bytes at
# most: a longer state dir gets its Ray temp dir under /tmp.
RAY_TEMP_MAX_CHARS = 40


# ---------------------------------------------------------------- Ray


def ray_env(token_path: Path, tracking: dict[str, str]) -> dict[str, str]:
    """The environment of Ray's processes and of its clients: token authentication on, with this cluster's token
    file (not ~/.ray/auth_token, which other Ray instances on the machine share), and this Python's scripts first on
    PATH, so that a job's `python -m orchestrator` runs in the environment that started the cluster. `tracking`
    (MLFLOW_TRACKING_USERNAME / _PASSWORD) is inherited by every job: whoever holds the Ray token can run code on
    the nodes anyway."""
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_AUTH_TOKEN", "RAY_ADDRESS")}
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(token_path), RAY_USAGE_STATS_ENABLED="0")
    env.update(tracking)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return env


def ray_temp_dir(state_dir: Path) -> tuple[Path, bool]:
    """Ray's --temp-dir: `<state-dir>/ray` when short enough for its sockets, else `ray` in a directory under /tmp
    named in `<state-dir>/ray-temp-dir` and used again by the next `up` (the bool: outside the state dir). Ray
    makes its temp dir 0777; the 0700 directory above it keeps other users out. `down` keeps it either way: the
    working dirs of `ray job submit --working-dir` jobs, and what they wrote there, are in it."""
    inside = state_dir / "ray"
    if len(str(inside)) <= RAY_TEMP_MAX_CHARS:
        return private_dir(inside), False
    outside = kept_dir(state_dir, "ray-temp-dir", "mocap-ray-") / "ray"
    outside.mkdir(exist_ok=True)
    return outside, True


def write_token(path: Path) -> str:
    """A fresh cluster token (256 bits, as `ray get-auth-token --generate` makes), readable by this user only."""
    token = secrets.token_hex(32)
    private_dir(path.parent)
    write_secret(path, token)
    return token


def _ray_node_ports() -> list[str]:
    names = ["--node-manager-port", "--object-manager-port", "--dashboard-agent-listen-port"]
    names += ["--dashboard-agent-grpc-port", "--runtime-env-agent-port", "--metrics-export-port"]
    return [x for name, port in zip(names, free_ports(len(names)), strict=True) for x in (name, str(port))]


def alive_nodes(dashboard: str, token: str) -> list[dict[str, Any]]:
    data = http_json(f"{dashboard}/api/v0/nodes?limit=100", token)
    return [n for n in data["data"]["result"]["result"] if n["state"] == "ALIVE"]


def start_ray_head(
    temp_dir: Path, logs: Path, env: dict[str, str], cpus: int, store_mb: int, timeout_s: float, register
):
    """`ray start --head --block`: GCS, dashboard on 127.0.0.1 (jobs API, state API) and a raylet with `cpus`.
    `register(record)` is called as soon as the process runs (and the record grows until it answers)."""
    gcs_port, dashboard_port, client_port = free_ports(3)
    command = [sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block"]
    command += ["--node-ip-address", HOST, "--port", str(gcs_port), "--ray-client-server-port", str(client_port)]
    command += ["--include-dashboard", "true", "--dashboard-host", HOST, "--dashboard-port", str(dashboard_port)]
    command += ["--num-cpus", str(cpus), "--object-store-memory", str(store_mb * 2**20), "--temp-dir", str(temp_dir)]
    command += ["--disable-usage-stats", *_ray_node_ports()]
    record = start_session(command, logs / "ray-head.log", env)
    dashboard = f"http://{HOST}:{dashboard_port}"
    token = Path(env["RAY_AUTH_TOKEN_PATH"]).read_text()
    record.update(gcs_address=f"{HOST}:{gcs_port}", dashboard_url=dashboard, num_cpus=cpus)
    register(record)

    def ready() -> bool:
        heads = [n for n in alive_nodes(dashboard, token) if n["is_head_node"]]
        http_json(f"{dashboard}/api/jobs/", token)  # the jobs API answers too
        if heads:
            record["node_id"] = heads[0]["node_id"]
        return bool(heads)

    what = f"Ray head (dashboard {dashboard}, GCS {record['gcs_address']})"
    wait_until(what, ready, timeout_s, record["log"], record)
    return record


def start_ray_node(
    head: dict[str, Any], index: int, temp_dir: Path, logs: Path, env, cpus, store_mb, timeout_s, register
):
    """`ray start --address <head> --block` with `cpus` logical CPUs: another node of the cluster on this machine."""
    command = [sys.executable, "-m", "ray.scripts.scripts", "start", "--address", head["gcs_address"], "--block"]
    command += ["--num-cpus", str(cpus), "--object-store-memory", str(store_mb * 2**20), "--temp-dir", str(temp_dir)]
    command += ["--disable-usage-stats", *_ray_node_ports()]
    token = Path(env["RAY_AUTH_TOKEN_PATH"]).read_text()
    known = {head["node_id"], *head.get("joined", [])}
    record = start_session(command, logs / f"ray-node-{index}.log", env)
    record["num_cpus"] = cpus
    register(record)

    def joined() -> bool:
        new = [n["node_id"] for n in alive_nodes(head["dashboard_url"], token) if n["node_id"] not in known]
        if new:
            record["node_id"] = new[0]
        return bool(new)

    wait_until(f"Ray node {index} (joining {head['gcs_address']})", joined, timeout_s, record["log"], record)
    head.setdefault("joined", []).append(record["node_id"])
    return record


# ---------------------------------------------------------------- PostgreSQL


def pg_bindir() -> Path:
    """PostgreSQL's server programs: $PG_BIN, else the directory of `pg_ctl` on PATH, else Debian's newest."""
    candidates = [os.environ.get("PG_BIN", "")]
    on_path = shutil.which("pg_ctl")
    candidates.append(str(Path(on_path).parent) if on_path else "")
    candidates += sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(Path(p).parent.name), reverse=True)
    for c in candidates:
        if c and (Path(c) / "initdb").exists() and (Path(c) / "pg_ctl").exists():
            return Path(c)
    raise ServiceError("PostgreSQL server not found (initdb, pg_ctl): run `make system-packages` or set PG_BIN")


def _as_pg_owner(command: list[str]) -> list[str]:
    """As root, run `command` as the `postgres` OS user (runuser, else su); otherwise as is."""
    if os.geteuid() != 0:
        return command
    if shutil.which("runuser"):
        return ["runuser", "-u", PG_OS_USER, "--", *command]
    return ["su", PG_OS_USER, "-s", "/bin/sh", "-c", shlex.join(command)]


def _run(command: list[str], what: str, log: Path, timeout_s: float) -> None:
    try:
        proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as e:
        raise ServiceError(f"{what} did not finish within {timeout_s:.0f} s; see its log {log}") from e
    if proc.returncode != 0:
        with open(log, "a") as f:
            f.write(proc.stdout + proc.stderr)
        last = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise ServiceError(f"{what} failed ({last[0]}); see its log {log}")


def pg_home(state_dir: Path) -> tuple[Path, bool]:
    """Where the database lives (mode 0700): `<state-dir>/postgres`, or, as root when the `postgres` user cannot
    reach the state dir (a 0700 state dir of root's), a directory under /tmp owned by `postgres`, named in
    `<state-dir>/postgres-home` and used again by every later `up` (the bool: outside the state dir)."""
    home = private_dir(state_dir / "postgres")
    if os.geteuid() != 0:
        return home, False
    shutil.chown(home, PG_OS_USER, PG_OS_USER)
    probe = subprocess.run(_as_pg_owner(["test", "-w", str(home)]), capture_output=True)
    if probe.returncode == 0:
        return home, False
    return kept_dir(state_dir, "postgres-home", "mocap-pg-", owner=pwd.getpwnam(PG_OS_USER).pw_uid), True


def start_postgres(state_dir: Path, home: Path, external: bool, timeout_s: float, register) -> dict[str, Any]:
    """initdb (once: the database persists across up/down in the state dir) and `pg_ctl start` on 127.0.0.1 at a
    free port, no unix socket, password authentication; then the database `mlflow`. `register(record)` is called
    before the server starts."""
    import psycopg2

    bindir = pg_bindir()
    data, log = home / "data", home / "postgres.log"
    password_file = state_dir / "postgres-password"
    record = {"home": str(home), "external": external, "bindir": str(bindir), "data_dir": str(data), "log": str(log)}
    record["password_file"] = str(password_file)
    register(record)
    if not (data / "PG_VERSION").exists():
        password = new_password()
        write_secret(password_file, password)
        pwfile = home / "initdb-password"
        write_secret(pwfile, password + "\n")
        if os.geteuid() == 0:
            shutil.chown(pwfile, PG_OS_USER, PG_OS_USER)
        initdb = [str(bindir / "initdb"), "-D", str(data), "-U", PG_USER, f"--pwfile={pwfile}"]
        initdb += ["--auth=scram-sha-256", "--encoding=UTF8", "--no-instructions"]
        try:
            _run(_as_pg_owner(initdb), f"initdb of {data}", state_dir / "logs" / "initdb.log", timeout_s)
        finally:
            pwfile.unlink(missing_ok=True)
    password = read_secret(password_file)
    (port,) = free_ports(1)
    options = f"-h {HOST} -p {port} -k ''"
    start = [str(bindir / "pg_ctl"), "-D", str(data), "-l", str(log), "-o", options, "-w", "-t", str(int(timeout_s))]
    _run(_as_pg_owner([*start, "start"]), f"PostgreSQL on {HOST}:{port}", log, timeout_s + 10)
    record.update(host=HOST, port=port, user=PG_USER, uri=f"postgresql://{PG_USER}@{HOST}:{port}/{PG_USER}")
    # SQLAlchemy 2.1 maps a bare postgresql:// to psycopg 3; the project installs psycopg2.
    record["sqlalchemy_uri"] = record["uri"].replace("postgresql://", "postgresql+psycopg2://", 1)
    register(record)

    def has_database() -> bool:
        """The tracking database and the auth app's user database, created when missing."""
        conn = psycopg2.connect(host=HOST, port=port, user=PG_USER, password=password, dbname="postgres")
        try:
            conn.autocommit = True
            with conn.cursor() as cur:
                for name in (PG_USER, mlflow_auth.AUTH_DATABASE):
                    cur.execute("SELECT 1 FROM pg_database WHERE datname = %s", (name,))
                    if cur.fetchone() is None:
                        cur.execute(f'CREATE DATABASE "{name}"')
        finally:
            conn.close()
        return True

    wait_until(f"PostgreSQL on {HOST}:{port}", has_database, timeout_s, log, retry_on=(psycopg2.OperationalError,))
    return record


def stop_postgres(record: dict[str, Any], logs: Path) -> None:
    """`pg_ctl stop -m fast` on the recorded data directory, which stays where it is, wherever that is (an outside
    home's log is copied into logs/ too)."""
    pg_ctl = [str(Path(record["bindir"]) / "pg_ctl"), "-D", record["data_dir"], "stop", "-m", "fast", "-w", "-t", "30"]
    if (Path(record["data_dir"]) / "postmaster.pid").exists():
        _run(_as_pg_owner(pg_ctl), f"pg_ctl stop of {record['data_dir']}", Path(record["log"]), 40)
    if record.get("external") and Path(record["log"]).exists():
        shutil.copy(record["log"], logs / "postgres.log")


def postgres_answers(record: dict[str, Any]) -> bool:
    import psycopg2

    try:
        password = read_secret(Path(record["password_file"]))
        psycopg2.connect(record["uri"], password=password, connect_timeout=3).close()
        return True
    except (psycopg2.Error, OSError):
        return False


# ---------------------------------------------------------------- MLflow


def mlflow_credentials(state_dir: Path) -> dict[str, str]:
    """The MLflow users' password files (0600, made once and kept: the user database keeps them too): the admin's
    and the lab user's, which jobs log as."""
    admin_file, user_file = state_dir / "mlflow-admin-password", state_dir / "mlflow-password"
    read_secret(admin_file, new_password)
    read_secret(user_file, new_password)
    return {"user": mlflow_auth.LAB_USER, "password_file": str(user_file), "admin_password_file": str(admin_file)}


def tracking_env(credentials: dict[str, str]) -> dict[str, str]:
    """A client's MLflow credentials (the environment variables MLflow's client reads), from `mlflow_credentials`."""
    password = read_secret(Path(credentials["password_file"]))
    return {"MLFLOW_TRACKING_USERNAME": credentials["user"], "MLFLOW_TRACKING_PASSWORD": password}


def start_mlflow(
    postgres: dict[str, Any], credentials: dict[str, str], state_dir: Path, timeout_s: float, register
) -> dict[str, Any]:
    """`mlflow server --app-name basic-auth` on PostgreSQL with proxied artifacts (clients upload through it to
    `<state-dir>/artifacts`), then the lab's user in its user database. Every request but /health needs a user;
    the passwords travel in the environment (PGPASSWORD, MLFLOW_AUTH_ADMIN_PASSWORD), not on the command line or
    in the auth config."""
    mlflow_auth.require_auth_app()
    (port,) = free_ports(1)
    artifacts, logs = private_dir(state_dir / "artifacts"), state_dir / "logs"
    config = state_dir / "mlflow-auth.ini"
    auth_db = f"postgresql+psycopg2://{PG_USER}@{HOST}:{postgres['port']}/{mlflow_auth.AUTH_DATABASE}"
    mlflow_auth.write_config(config, auth_db)
    admin_password = read_secret(Path(credentials["admin_password_file"]))
    command = [sys.executable, "-m", "mlflow", "server", "--app-name", "basic-auth"]
    command += ["--backend-store-uri", postgres["sqlalchemy_uri"], "--artifacts-destination", str(artifacts)]
    command += ["--host", HOST, "--port", str(port), "--workers", "2"]
    env = dict(os.environ, PGPASSWORD=read_secret(Path(postgres["password_file"])))
    env.update(mlflow_auth.server_env(config, admin_password))
    for key in ("MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD", "MLFLOW_TRACKING_URI"):
        env.pop(key, None)
    env.setdefault("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")
    env.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    record = start_session(command, logs / "mlflow.log", env)
    record.update(uri=f"http://{HOST}:{port}", artifacts=str(artifacts), auth_config=str(config), **credentials)
    register(record)
    health = f"{record['uri']}/health"
    wait_until(f"MLflow server {record['uri']}", lambda: http_ok(health), timeout_s, record["log"], record)
    password = read_secret(Path(credentials["password_file"]))
    mlflow_auth.ensure_user(
        record["uri"], admin_password, credentials["user"], password, credentials["admin_password_file"]
    )
    return record


def stop(record: dict[str, Any] | None) -> None:
    if record is not None:
        stop_session(record)
