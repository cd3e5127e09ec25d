"""Tracking: the `Tracker` interface and its no-op twin (`base`), the MLflow tracker with its disk
spool (`mlflow`), and a local MLflow server for parallel jobs (`server`).

This is the only package that imports mlflow, and only `orchestrator.tracking.mlflow` does: importing
`orchestrator.tracking` or `orchestrator.tracking.base` does not load it (the server runs as a subprocess).
"""

from orchestrator.tracking.base import NoOpTracker, Tracker, flatten

__all__ = ["NoOpTracker", "Tracker", "flatten"]
