"""Tracking: the `RunLogger` interface and its no-op twin (`base`), the MLflow logger (`mlflow`) with its disk
spool drained in the background (`spool`, the file itself in `spoolfile`), a local MLflow server for parallel
jobs (`server`), the store's URIs, which ones MLflow can use and their credentials masked (`uri`), runs read
back from a store (`query`), who this process is to the server and what it may do (`identity`), MLflow's
basic-auth app and its users (`mlflow_auth`), private directories and secret files (`secret_files`), system
metrics (`system`) and the trained policy as an MLflow model (`model`).

This is the only package that imports mlflow, and importing `orchestrator.tracking`,
`orchestrator.tracking.base` or `orchestrator.tracking.uri` does not load it (the server runs as a
subprocess).
"""

from orchestrator.tracking.base import NoOpLogger, RunLogger, flatten

__all__ = ["NoOpLogger", "RunLogger", "flatten"]
