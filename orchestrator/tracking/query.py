"""Reading runs back: the children of a sweep's parent run, for the sweep's comparison."""

from __future__ import annotations

from typing import Any

from mlflow.tracking import MlflowClient


def child_runs(uri: str, parent_run_id: str) -> list[dict[str, Any]]:
    """Every run whose parent is `parent_run_id`: run_id, name, status, params and latest metrics."""
    client = MlflowClient(uri)
    parent = client.get_run(parent_run_id)
    runs = client.search_runs(
        [parent.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent_run_id}'", max_results=10_000
    )
    return [
        {
            "run_id": r.info.run_id,
            "name": r.info.run_name,
            "status": r.info.status,
            "params": dict(r.data.params),
            "metrics": dict(r.data.metrics),
        }
        for r in runs
    ]
