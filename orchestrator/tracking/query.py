"""The store's runs, read back and touched outside a run's own logger: every `MlflowClient` call of the service.

A finished stage's artifacts, metrics, tags and provenance (`orchestrator.upstream`), the newest finished
run with a stage hash in the experiments a run trusts (`orchestrator.stages`), whether a resumed run is
still in the store (`orchestrator.preflight`), a run's artifact root (the closing summary), a sweep's
children and their histories (`orchestrator.sweep`), a sweep's experiment and its parent run's end, a
run's metric steps (`orchestrator.bench.chaos`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from orchestrator.tracking.base import EXPERIMENT_TAGS, store_artifacts
from orchestrator.tracking.manifest import COMPLETE_TAG


def MlflowClient(uri: str):  # noqa: N802 - stands in for the class it returns an instance of
    """mlflow's `MlflowClient(uri)`, imported on the first call: a run that tracks nothing (`tracking=off`, the
    benchmarks) then never imports mlflow and its dependencies."""
    from mlflow.tracking import MlflowClient as client

    return client(uri)


def download_artifact(uri: str, run_id: str, path: str, dest: Path) -> Path:
    """Run `run_id`'s artifact `path`, downloaded under `dest`; the local path."""
    return Path(MlflowClient(uri).download_artifacts(run_id, path, str(dest)))


def list_artifacts(uri: str, run_id: str, path: str) -> list[str]:
    """The artifact paths of run `run_id` under `path`."""
    return [a.path for a in MlflowClient(uri).list_artifacts(run_id, path)]


def run_metrics(uri: str, run_id: str) -> dict[str, float]:
    """The latest value of each of the run's metrics."""
    return dict(MlflowClient(uri).get_run(run_id).data.metrics)


def run_status_and_tags(uri: str, run_id: str) -> tuple[str, dict[str, str]]:
    """The run's status (DELETED for a deleted run the store keeps for undeletion) and its tags."""
    r = MlflowClient(uri).get_run(run_id)
    return ("DELETED" if r.info.lifecycle_stage == "deleted" else r.info.status), dict(r.data.tags)


def run_exists(uri: str, run_id: str) -> bool | None:
    """Whether the store has run `run_id` (a deleted run it keeps for undeletion counts as gone); None when the
    store does not answer (MLflow's requests time out after 3 s, `orchestrator.tracking.spool`)."""
    from orchestrator.tracking.spool import refused  # sets MLflow's request timeout and retries for the process

    try:
        return MlflowClient(uri).get_run(run_id).info.lifecycle_stage != "deleted"
    except Exception as e:
        return False if refused(e) else None


def artifact_root(uri: str, run_id: str) -> str:
    """Where the run's artifacts are (a local directory for a SQLite store)."""
    return MlflowClient(uri).get_run(run_id).info.artifact_uri.removeprefix("file://")


def find_finished(uri: str, stage_hash: str, experiments: list[str], only: dict[str, str] | None = None) -> str | None:
    """The newest complete run with this stage hash in the named experiments (`complete_runs`)."""
    runs = complete_runs(uri, stage_hash, experiments, limit=1, only=only)
    return runs[0][0] if runs else None


def complete_runs(
    uri: str, stage_hash: str, experiments: list[str], limit: int = 5, only: dict[str, str] | None = None
) -> list[tuple[str, str]]:
    """(run id, manifest digest) of the newest `limit` FINISHED runs with this stage hash whose artifacts all
    landed (the tag `manifest.COMPLETE_TAG`), newest first, in the named experiments ("*": any experiment of the
    store; names the store does not have are skipped); in an experiment `only` maps to a user, only runs recorded
    as that user's. Deleted runs are never among them."""
    client = MlflowClient(uri)
    if "*" in experiments:
        found = list(client.search_experiments())
    else:
        found = [e for e in (client.get_experiment_by_name(n) for n in dict.fromkeys(experiments)) if e is not None]
    users = {e.experiment_id: (only or {}).get(e.name) for e in found}
    if not users:
        return []
    runs = client.search_runs(
        list(users),
        filter_string=f"tags.stage_hash = '{stage_hash}' and attributes.status = 'FINISHED'",
        order_by=["attributes.start_time DESC"],
        max_results=100,
    )
    mine = [r for r in runs if users[r.info.experiment_id] in (None, r.info.user_id)]
    complete = [(r.info.run_id, r.data.tags[COMPLETE_TAG]) for r in mine if r.data.tags.get(COMPLETE_TAG)]
    return complete[:limit]


# What `run_provenance` says of a run.
PROVENANCE = ("experiment", "user", "git_commit")


def run_provenance(uri: str, run_id: str) -> dict[str, str]:
    """Who made run `run_id`, where and with what code: its experiment's name, its user and its git commit."""
    client = MlflowClient(uri)
    r = client.get_run(run_id)
    experiment = client.get_experiment(r.info.experiment_id)
    return {
        "experiment": experiment.name if experiment else r.info.experiment_id,
        "user": r.data.tags.get("mlflow.user") or r.info.user_id or "unknown",
        "git_commit": r.data.tags.get("git_commit", "unknown"),
    }


def metric_steps(uri: str, run_id: str, key: str) -> list[int]:
    """The steps at which the run logged `key`, in the order the store returns them."""
    return [m.step for m in MlflowClient(uri).get_metric_history(run_id, key)]


def set_terminated(uri: str, run_id: str, status: str) -> None:
    MlflowClient(uri).set_terminated(run_id, status)


def ensure_experiment(uri: str, name: str) -> None:
    """Experiment `name` in the store, created (with its artifacts beside a SQLite store) if missing."""
    client = MlflowClient(uri)
    if client.get_experiment_by_name(name) is None:
        client.create_experiment(name, artifact_location=store_artifacts(uri), tags=EXPERIMENT_TAGS)


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
