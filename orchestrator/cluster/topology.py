"""The cluster's lifecycle, recorded in `<state-dir>/cluster.json`: `up`, `down`, `status` and a client's `env`.

`up` starts, each in its own process session and each waited for until it answers:
- a Ray head (`ray start --head`: GCS, dashboard and jobs API on 127.0.0.1, token authentication on, with
  this cluster's own token in `<state-dir>/ray-auth-token`) and `--nodes` more Ray nodes joining it, each
  with its own logical CPUs, its own ports and a Ray temp dir of its own (no clash with other Rays here);
- PostgreSQL (initdb once into the state dir, pg_ctl on 127.0.0.1 at a free port) with a database `mlflow`;
- `mlflow server --app-name basic-auth` on that database, artifacts proxied into `<state-dir>/artifacts` (clients
  log to `mlflow-artifacts:` through the server); every request needs a user (`orchestrator.tracking.mlflow_auth`),
  and jobs log as the lab's user, whose credentials the Ray nodes pass to every job.
The addresses go to stdout and to `<state-dir>/cluster.json`; logs to `<state-dir>/logs/`; the state dir is 0700
and each password and token in it 0600. `down` stops only what `up` recorded there (never `ray stop`, which would
stop every Ray on the machine) and deletes nothing else: the database (wherever it lives), the artifacts, the
passwords and Ray's temp dir (jobs' working dirs) stay for the next `up`. A service that does not come up stops
everything started so far and exits with one line naming it and its log.
"""

from __future__ import annotations

import json
import shlex
import time
from pathlib import Path
from typing import Any

from orchestrator.cluster import services as svc
from orchestrator.cluster.procs import alive, http_ok
from orchestrator.errors import ServiceError
from orchestrator.tracking.secret_files import private_dir, write_secret

STATE_FILE = "cluster.json"
DEFAULT_STATE_DIR = ".cluster"


def state_path(state_dir: Path) -> Path:
    return state_dir / STATE_FILE


def load_state(state_dir: Path) -> dict[str, Any] | None:
    path = state_path(state_dir)
    return json.loads(path.read_text()) if path.exists() else None


def save_state(state: dict[str, Any]) -> None:
    """Written after every service that comes up, so that `down` can stop a half-started cluster."""
    path = state_path(Path(state["state_dir"]))
    tmp = path.with_suffix(".tmp")
    write_secret(tmp, json.dumps(state, indent=2))
    tmp.replace(path)


def client_env(state: dict[str, Any]) -> dict[str, str]:
    """What a client of this cluster needs in its environment: Ray's token, the GCS (a driver's `ray.init("auto")`,
    i.e. `runtime.address=auto`), the jobs API (`ray job submit`, `ray list actors`), the tracking URI (no
    credentials in it) and the MLflow user; its password is in `client_secret_files`."""
    env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": state["ray"]["auth_token_path"]}
    env["RAY_ADDRESS"] = state["ray"]["head"]["gcs_address"]
    env["RAY_API_SERVER_ADDRESS"] = state["ray"]["head"]["dashboard_url"]
    if state.get("mlflow"):
        env["MLFLOW_TRACKING_URI"] = state["mlflow"]["uri"]
        env["MLFLOW_TRACKING_USERNAME"] = state["mlflow"]["user"]
    return env


def client_secret_files(state: dict[str, Any]) -> dict[str, str]:
    """{variable: the 0600 file holding its value}: `env` prints `export VAR="$(cat FILE)"`, never the secret."""
    return {"MLFLOW_TRACKING_PASSWORD": state["mlflow"]["password_file"]} if state.get("mlflow") else {}


def summary(state: dict[str, Any]) -> dict[str, Any]:
    """The addresses a user needs (no secrets: the token and the password stay in their files)."""
    ray, pg, ml = state.get("ray") or {}, state.get("postgres") or {}, state.get("mlflow") or {}
    head = ray.get("head") or {}
    nodes = [{"node_id": head.get("node_id"), "cpus": head.get("num_cpus"), "head": True}]
    nodes += [{"node_id": n.get("node_id"), "cpus": n.get("num_cpus"), "head": False} for n in ray.get("nodes", [])]
    return {
        "state_dir": state["state_dir"],
        "ray_dashboard": head.get("dashboard_url"),
        "ray_gcs_address": head.get("gcs_address"),
        "ray_auth_token_path": ray.get("auth_token_path"),
        "ray_nodes": nodes,
        "mlflow_tracking_uri": ml.get("uri"),
        "mlflow_user": ml.get("user"),
        "mlflow_password_file": ml.get("password_file"),
        "mlflow_admin_password_file": ml.get("admin_password_file"),
        "mlflow_artifacts": ml.get("artifacts"),
        "postgres_uri": pg.get("uri"),
        "postgres_password_file": pg.get("password_file"),
        "logs": str(Path(state["state_dir"]) / "logs"),
    }


def print_summary(state: dict[str, Any], as_json: bool) -> None:
    info = summary(state)
    if as_json:
        print(json.dumps(info, indent=2))
        return
    nodes = ", ".join(f"{'head' if n['head'] else 'node'} {n['cpus']} CPU" for n in info["ray_nodes"])
    print(f"Ray dashboard   {info['ray_dashboard']}   (jobs: ray job submit --address {info['ray_dashboard']})")
    print(f"Ray GCS         {info['ray_gcs_address']}   ({nodes}; token in {info['ray_auth_token_path']})")
    print(f"MLflow          {info['mlflow_tracking_uri']}   (artifacts proxied into {info['mlflow_artifacts']})")
    user, password, admin = info["mlflow_user"], info["mlflow_password_file"], info["mlflow_admin_password_file"]
    print(f"MLflow users    {user} (jobs; password in {password}), admin (password in {admin})")
    print(f"PostgreSQL      {info['postgres_uri']}   (password in {info['postgres_password_file']})")
    print(f"State           {state_path(Path(info['state_dir']))}; logs in {info['logs']}")
    env_command = f"python -m orchestrator.cluster env --state-dir {shlex.quote(info['state_dir'])}"
    print(f'Clients         eval "$({env_command})"   (Ray token, addresses, MLflow user and password)')


def records(state: dict[str, Any]) -> list[tuple[str, dict[str, Any] | None]]:
    """Every recorded process, in stopping order: MLflow, the joined Ray nodes, the Ray head."""
    ray = state.get("ray") or {}
    out: list[tuple[str, dict[str, Any] | None]] = [("MLflow server", state.get("mlflow"))]
    out += [(f"Ray node {i}", n) for i, n in reversed(list(enumerate(ray.get("nodes", []), start=1)))]
    out.append(("Ray head", ray.get("head")))
    return out


def running(state: dict[str, Any]) -> bool:
    pg = state.get("postgres")
    return any(alive(r) for _, r in records(state)) or bool(pg and svc.postgres_answers(pg))


def up(state_dir: Path, head_cpus: int, node_cpus: int, nodes: int, store_mb: int, timeout_s: float) -> dict:
    previous = load_state(state_dir)
    if previous is not None and running(previous):
        raise ServiceError(f"a cluster is already up from {state_path(state_dir)}; run `down` first")
    if previous is not None:  # a stale record (processes gone, e.g. after a reboot): clear what it left
        down(state_dir, quiet=True)
    private_dir(state_dir)
    logs = private_dir(state_dir / "logs")
    temp_dir, temp_external = svc.ray_temp_dir(state_dir)
    token_path = state_dir / "ray-auth-token"
    svc.write_token(token_path)
    credentials = svc.mlflow_credentials(state_dir)
    state: dict[str, Any] = {"state_dir": str(state_dir), "started": time.time()}
    state["ray"] = {"temp_dir": str(temp_dir), "temp_external": temp_external, "auth_token_path": str(token_path)}
    save_state(state)

    def register(*keys: str):
        """Record a process in the state file as soon as it runs, so that `down` stops it even mid-start."""

        def put(record: dict[str, Any]) -> None:
            target = state
            for key in keys[:-1]:
                target = target[key]
            if isinstance(target[keys[-1]], list):
                target[keys[-1]].append(record)
            else:
                target[keys[-1]] = record
            save_state(state)

        return put

    try:
        env = svc.ray_env(token_path, svc.tracking_env(credentials))
        state["ray"].update(head=None, nodes=[])
        head = svc.start_ray_head(temp_dir, logs, env, head_cpus, store_mb, timeout_s, register("ray", "head"))
        for i in range(1, nodes + 1):
            svc.start_ray_node(head, i, temp_dir, logs, env, node_cpus, store_mb, timeout_s, register("ray", "nodes"))
        save_state(state)  # the node ids found while waiting
        home, external = svc.pg_home(state_dir)
        state["postgres"] = {"home": str(home), "external": external}
        save_state(state)
        svc.start_postgres(state_dir, home, external, timeout_s, register("postgres"))
        state["mlflow"] = None
        svc.start_mlflow(state["postgres"], credentials, state_dir, timeout_s, register("mlflow"))
        save_state(state)
    except BaseException:
        down(state_dir, quiet=True)
        raise
    return state


def down(state_dir: Path, quiet: bool = False) -> bool:
    """Stop what `up` recorded in the state dir, deleting no data (the database, wherever it lives; Ray's temp
    dir with jobs' working dirs; the artifacts); False when nothing was recorded."""
    state = load_state(state_dir)
    if state is None:
        return False
    errors = []
    for name, record in records(state):
        if record is not None and alive(record) and not quiet:
            print(f"stopping {name} (pid {record['pid']})")
        try:
            svc.stop(record)
        except Exception as e:  # go on: the other services still have to stop
            errors.append(f"{name}: {e}")
    pg = state.get("postgres") or {}
    try:
        if pg.get("data_dir"):
            if not quiet and (Path(pg["data_dir"]) / "postmaster.pid").exists():
                print(f"stopping PostgreSQL ({pg['data_dir']})")
            svc.stop_postgres(pg, state_dir / "logs")
    except ServiceError as e:
        errors.append(str(e))
    if not quiet:
        for what, where in (
            ("database", pg.get("data_dir")),
            ("Ray temp dir", (state.get("ray") or {}).get("temp_dir")),
        ):
            if where and not Path(where).is_relative_to(state_dir):
                print(f"kept the {what} in {where}")
    state_path(state_dir).unlink(missing_ok=True)
    if errors:
        raise ServiceError("; ".join(errors))
    return True


def status(state_dir: Path) -> dict[str, Any]:
    """Each service's state: up (its process runs and it answers) or down."""
    state = load_state(state_dir)
    if state is None:
        raise ServiceError(f"no cluster recorded in {state_path(state_dir)}; run `up`")
    token = Path(state["ray"]["auth_token_path"]).read_text()
    services = {}
    head = state["ray"].get("head")
    try:
        alive_nodes = svc.alive_nodes(head["dashboard_url"], token) if alive(head) else []
    except OSError:
        alive_nodes = []
    ids = {n["node_id"] for n in alive_nodes}
    for name, record in records(state):
        if name.startswith("Ray"):
            services[name] = "up" if alive(record) and record.get("node_id") in ids else "down"
    ml = state.get("mlflow")
    services["MLflow server"] = "up" if alive(ml) and http_ok(f"{ml['uri']}/health") else "down"
    pg = state.get("postgres")
    services["PostgreSQL"] = "up" if pg and pg.get("uri") and svc.postgres_answers(pg) else "down"
    return {**summary(state), "services": services}
