"""MLflow's basic-auth app for a tracking server (the cluster's, a parallel sweep's): its config, its secrets and the
lab's user.

`mlflow server --app-name basic-auth` answers 401 to any request without a valid user and password (only
`/health` and static files are open). Its users live in a database of their own (`mlflow_auth`, beside the
tracking database `mlflow`). The admin is created the first time the app meets an empty user store, with
the password in `MLFLOW_AUTH_ADMIN_PASSWORD` (MLflow ships none); the config file holds no secret.
`default_permission = READ`: every user can read every run, and only a run's or an experiment's creator (and
the admin) can change it, so one user cannot overwrite another's runs, artifacts or models.

Jobs log as the lab's user (`lab`, a non-admin), with `MLFLOW_TRACKING_USERNAME` / `MLFLOW_TRACKING_PASSWORD`
in their environment; the tracking URI carries no credentials. `ensure_user` creates that user, or sets its
password to the one given, through the admin's REST API.

    python -m orchestrator.tracking.mlflow_auth http://mlflow:5000   # the same, for docker/compose.yaml
        # env: MLFLOW_AUTH_ADMIN_PASSWORD, MLFLOW_TRACKING_USERNAME, MLFLOW_TRACKING_PASSWORD
"""

from __future__ import annotations

import base64
import configparser
import importlib.util
import io
import json
import os
import secrets
import sys
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from orchestrator.errors import ServiceError
from orchestrator.tracking.secret_files import write_secret

ADMIN_USER = "admin"  # MLflow's default admin name; its password is ours
LAB_USER = "lab"  # the user jobs log as
AUTH_DATABASE = "mlflow_auth"
DEFAULT_PERMISSION = "READ"
# The server checks a password with scrypt (werkzeug's default), a third of a second of CPU on a busy two-core
# machine, at every request unless it remembers a success: for this long, per worker (keyed by an HMAC of the
# password). A password changed or a user deleted through another worker is still accepted by this one for
# at most that long.
AUTH_CACHE_S = 60


def require_auth_app() -> None:
    """MLflow's auth app imports Flask-WTF (the `mlflow[auth]` extra): a one-line error when it is missing."""
    if importlib.util.find_spec("flask_wtf") is None:
        raise ServiceError(
            "MLflow's basic-auth app needs Flask-WTF: pip install -c constraints.txt -e . (mlflow[auth])"
        )


def write_config(path: Path, database_uri: str) -> None:
    """The auth app's ini (`MLFLOW_AUTH_CONFIG_PATH`): its user database and READ for everyone; no password in it
    (the database's comes from PGPASSWORD, the admin's from MLFLOW_AUTH_ADMIN_PASSWORD)."""
    config = configparser.ConfigParser()
    config["mlflow"] = {
        "default_permission": DEFAULT_PERMISSION,
        "database_uri": database_uri,
        "admin_username": ADMIN_USER,
        "authorization_function": "mlflow.server.auth:authenticate_request_basic_auth",
        "auth_cache_ttl_seconds": str(AUTH_CACHE_S),
    }
    text = io.StringIO()
    config.write(text)
    write_secret(path, text.getvalue())


def server_env(config_path: Path, admin_password: str) -> dict[str, str]:
    """What `mlflow server --app-name basic-auth` needs in its environment: the config, the admin's password for
    the first start, and a Flask secret key for the sign-up form's CSRF token (fresh each start)."""
    return {
        "MLFLOW_AUTH_CONFIG_PATH": str(config_path),
        "MLFLOW_AUTH_ADMIN_PASSWORD": admin_password,
        "MLFLOW_FLASK_SERVER_SECRET_KEY": secrets.token_hex(32),
    }


def _call(uri: str, method: str, path: str, auth: tuple[str, str], body: dict | None = None) -> tuple[int, str]:
    """(HTTP status, body) of one REST call to the server with basic authentication."""
    basic = base64.b64encode(f"{auth[0]}:{auth[1]}".encode()).decode()
    headers = {"Authorization": f"Basic {basic}", "Content-Type": "application/json"}
    data = json.dumps(body).encode() if body is not None else None
    request = urllib.request.Request(f"{uri}{path}", data=data, headers=headers, method=method)
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, response.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode(errors="replace")


def ensure_user(uri: str, admin_password: str, username: str, password: str, admin_file: str = "") -> None:
    """Create `username` (not an admin) with `password` on the server at `uri`, or set its password if it exists."""
    admin = (ADMIN_USER, admin_password)
    status, _ = _call(uri, "GET", f"/api/2.0/mlflow/users/get?{urllib.parse.urlencode({'username': username})}", admin)
    if status == 401:
        where = f" in {admin_file}" if admin_file else ""
        raise ServiceError(
            f"MLflow server {uri} refuses the admin password{where}: its user database keeps the admin's first "
            "password (change it with the update-password API, or drop the mlflow_auth database)"
        )
    if status == 200:
        body = {"username": username, "password": password}
        status, text = _call(uri, "PATCH", "/api/2.0/mlflow/users/update-password", admin, body)
    else:
        status, text = _call(
            uri, "POST", "/api/2.0/mlflow/users/create", admin, {"username": username, "password": password}
        )
    if status != 200:
        raise ServiceError(f"MLflow server {uri}: setting up user {username!r} failed ({status} {text[:200]})")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    uri = argv[0] if argv else os.environ.get("MLFLOW_TRACKING_URI", "")
    missing = [k for k in ("MLFLOW_AUTH_ADMIN_PASSWORD", "MLFLOW_TRACKING_PASSWORD") if not os.environ.get(k)]
    if not uri or missing:
        print(
            f"mlflow_auth: set {', '.join(missing) or 'the server URI (argument or MLFLOW_TRACKING_URI)'}",
            file=sys.stderr,
        )
        return 1
    username = os.environ.get("MLFLOW_TRACKING_USERNAME") or LAB_USER
    try:
        ensure_user(uri, os.environ["MLFLOW_AUTH_ADMIN_PASSWORD"], username, os.environ["MLFLOW_TRACKING_PASSWORD"])
    except (ServiceError, OSError) as e:
        print(f"mlflow_auth: {e}", file=sys.stderr)
        return 1
    print(f"MLflow user {username!r} ready on {uri}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
