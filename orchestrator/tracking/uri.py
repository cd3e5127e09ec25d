"""Tracking URIs, told without importing mlflow: the store a run writes to, and which URIs MLflow can use.

`store_uri` is the one place that says where a run (or a sweep) without `tracking.uri` keeps its records:
the embedded SQLite store `mlflow.db` in its directory. `tracking_uri_error` is asked at composition.
"""

from __future__ import annotations

import os
from importlib.metadata import entry_points
from pathlib import Path
from urllib.parse import urlparse

# The schemes of MLflow's own tracking stores (a bare path is a file store); plug-ins add theirs under
# the `mlflow.tracking_store` entry point. A database scheme may name its driver: postgresql+psycopg2.
TRACKING_SCHEMES = (
    "file", "sqlite", "postgresql", "mysql", "mssql", "http", "https", "databricks", "databricks-uc", "uc",
)  # fmt: skip


def tracking_uri_error(uri: str) -> str | None:
    """Why MLflow cannot use `uri` as a tracking store (an unknown scheme, a file store without the opt-in), or None."""
    if uri in ("databricks", "databricks-uc", "uc"):
        return None
    scheme = urlparse(uri).scheme  # as MLflow reads it
    if scheme in ("", "file") and os.environ.get("MLFLOW_ALLOW_FILE_STORE", "").lower() not in ("true", "1"):
        # MLflow 3's file store is in maintenance mode: it refuses to open without the opt-in.
        return (
            f"{uri!r} is an MLflow file store, which MLflow 3 opens only with MLFLOW_ALLOW_FILE_STORE=true; "
            "use sqlite:///PATH/mlflow.db (or leave tracking.uri unset: a SQLite store in the run directory)"
        )
    if not scheme or scheme.split("+")[0] in TRACKING_SCHEMES:
        return None
    plugins = {e.name for e in entry_points(group="mlflow.tracking_store")}
    if scheme in plugins:
        return None
    known = ", ".join(f"{s}:" for s in (*TRACKING_SCHEMES, *sorted(plugins)))
    return f"MLflow has no tracking store for the scheme {scheme!r} of {uri!r} (a path, or one of {known})"


def embedded_uri(directory: str | Path) -> str:
    """The tracking URI of the embedded store of a run (or sweep) directory: `<directory>/mlflow.db`."""
    return f"sqlite:///{Path(directory).resolve() / 'mlflow.db'}"


def store_uri(uri: str | None, directory: str | Path) -> str:
    """The store a run or sweep writes to: `tracking.uri` as given, else the embedded one in `directory`."""
    return uri or embedded_uri(directory)
