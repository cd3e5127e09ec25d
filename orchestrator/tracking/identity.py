"""Who an authenticated MLflow server says this process is, and what it lets that user do in an experiment.

MLflow's basic-auth app knows its users and gives the creator of an experiment MANAGE on it; it does not check the
user a run records (the client sends that name, `mlflow.user`, as it likes). So trust is read from the server:

- `whoami(uri)`: the user the server authenticates this process as (GET /api/2.0/mlflow/users/current), with the
  credentials of MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD or of the URI; None for a store without users
  (a file or SQLite store, a server without the auth app, one that does not answer);
- `experiment_access(uri, user, name)`: the experiment's id and the user's permission on it, as the server resolves
  it (GET /api/3.0/mlflow/users/permissions/get: its grants, then the default permission).

`orchestrator.stages.trusted_sources` turns these into the trust rule the README states; `orchestrator.preflight`
refuses a run whose own experiment this user may not write to, before anything trains.
"""

from __future__ import annotations

import base64
import json
import os
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from urllib.parse import unquote, urlsplit

# Permissions that let a user create runs in an experiment (MLflow's `Permission.can_update`).
WRITE = ("EDIT", "MANAGE")
UNKNOWN = "UNKNOWN"  # a server without MLflow 3's permission API: trusted for nothing, refused for nothing


@dataclass(frozen=True)
class Identity:
    user: str
    admin: bool


@dataclass(frozen=True)
class Access:
    experiment_id: str | None  # None: the server has no experiment of that name yet (or did not answer)
    permission: str  # READ, USE, EDIT, MANAGE, NO_PERMISSIONS (also: the server did not say); MANAGE for an
    # admin, and for an experiment not made yet

    @property
    def writable(self) -> bool:
        return self.permission in WRITE


def auth_header(uri: str) -> dict[str, str]:
    """The basic-auth header for an HTTP(S) tracking server: the URI's user and password, else those of
    MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD; no header when neither is there."""
    parts = urlsplit(uri)
    if parts.password is not None:
        user, password = unquote(parts.username or ""), unquote(parts.password)
    else:
        user, password = os.environ.get("MLFLOW_TRACKING_USERNAME"), os.environ.get("MLFLOW_TRACKING_PASSWORD")
    if user is None or password is None:
        return {}
    return {"Authorization": "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()}


def server_url(uri: str) -> str:
    """The server's URL without credentials or a trailing slash."""
    parts = urlsplit(uri)
    return parts._replace(netloc=parts.netloc.rpartition("@")[2]).geturl().rstrip("/")


def _get(uri: str, path: str, query: dict[str, str], timeout_s: float) -> tuple[int, dict]:
    """(HTTP status, JSON body) of one GET to the server: ({}) for a body that is not JSON, status 0 for no answer."""
    url = f"{server_url(uri)}{path}?{urllib.parse.urlencode(query)}" if query else f"{server_url(uri)}{path}"
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=auth_header(uri)), timeout=timeout_s) as r:
            status, body = r.status, r.read()
    except urllib.error.HTTPError as e:
        status, body = e.code, b""
    except OSError:
        return 0, {}
    try:
        answer = json.loads(body.decode() or "{}")
    except ValueError:
        answer = {}
    return status, answer if isinstance(answer, dict) else {}


# (server, credentials) -> who the server said they are; only answers are kept, so a server that did not answer is
# asked again next time.
_KNOWN: dict[tuple[str, str], Identity] = {}


def whoami(uri: str, timeout_s: float = 3.0) -> Identity | None:
    """The user the MLflow server at `uri` authenticates this process as; None for a store without users (and
    without credentials to give: a server that asks for a user is refused by `orchestrator.preflight`)."""
    header = auth_header(uri).get("Authorization")
    if urlsplit(uri).scheme not in ("http", "https") or header is None:
        return None
    key = (server_url(uri), header)
    if key not in _KNOWN:
        _, answer = _get(uri, "/api/2.0/mlflow/users/current", {}, timeout_s)
        user = answer.get("user")
        if not answer.get("is_basic_auth") or not isinstance(user, dict) or not user.get("username"):
            return None
        _KNOWN[key] = Identity(str(user["username"]), bool(user.get("is_admin")))
    return _KNOWN[key]


def experiment_access(uri: str, who: Identity, name: str, timeout_s: float = 3.0) -> Access:
    """Experiment `name`'s id on the server and `who`'s permission on it (NO_PERMISSIONS when the server does not
    say: trusted for nothing). One that does not exist yet is the user's to create: MANAGE."""
    status, found = _get(uri, "/api/2.0/mlflow/experiments/get-by-name", {"experiment_name": name}, timeout_s)
    experiment = found.get("experiment")
    if status == 404:
        return Access(None, "MANAGE")
    if status != 200 or not isinstance(experiment, dict) or "experiment_id" not in experiment:
        return Access(None, "NO_PERMISSIONS")
    experiment_id = str(experiment["experiment_id"])
    if who.admin:
        return Access(experiment_id, "MANAGE")
    query = {"username": who.user, "resource_type": "experiment", "resource_id": experiment_id}
    status, answer = _get(uri, "/api/3.0/mlflow/users/permissions/get", query, timeout_s)
    if status == 404:  # a server from before MLflow 3's permission API: it cannot say
        return Access(experiment_id, UNKNOWN)
    return Access(experiment_id, str(answer.get("permission") or "NO_PERMISSIONS"))
