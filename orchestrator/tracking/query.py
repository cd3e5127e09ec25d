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


def metric_histories(uri: str, run_ids: list[str], keys: list[str]) -> dict[str, dict[str, list[tuple[int, float]]]]:
    """{run_id: {metric: [(step, value), ...] in step order}} of the given runs and metrics."""
    client = MlflowClient(uri)
    out: dict[str, dict[str, list[tuple[int, float]]]] = {}
    for run_id in run_ids:
        out[run_id] = {}
        for key in keys:
            history = sorted((m.step, m.value) for m in client.get_metric_history(run_id, key))
            out[run_id][key] = history
    return out
