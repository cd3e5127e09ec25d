"""Old checkpoints leave the MLflow store as they leave the run directory: `delete_artifact` through the
tracker, in order after the uploads before it, on a real embedded store."""

from __future__ import annotations

from mlflow.tracking import MlflowClient

from orchestrator import checkpoint
from orchestrator.tracking.base import NoOpLogger
from orchestrator.tracking.mlflow import MlflowLogger


def stored(logger: MlflowLogger) -> list[str]:
    client = MlflowClient(logger.uri)
    return sorted(a.path for a in client.list_artifacts(logger.run_id, "checkpoints"))


def test_deleted_checkpoints_leave_the_store_and_the_kept_ones_stay(tmp_path):
    logger = MlflowLogger(None, "default", run_dir=tmp_path, background=False)
    ckpts = tmp_path / "checkpoints"
    for i in range(1, 5):  # as Trainer.save: upload, then prune here and there
        path = checkpoint.save(ckpts, i, {"w": i})
        logger.log_artifact(path, "checkpoints")
        checkpoint.prune(ckpts, keep=2, forget=lambda old: logger.delete_artifact(f"checkpoints/{old.name}"))
    assert stored(logger) == ["checkpoints/ckpt-0000003.pt", "checkpoints/ckpt-0000004.pt"]
    logger.delete_artifact("checkpoints/ckpt-0000001.pt")  # gone already: nothing to do, nothing spooled
    logger.close()
    assert logger.pending() == 0
    assert stored(logger) == ["checkpoints/ckpt-0000003.pt", "checkpoints/ckpt-0000004.pt"]


def test_the_untracked_logger_accepts_a_delete():
    NoOpLogger().delete_artifact("checkpoints/ckpt-0000001.pt")  # no store: nothing to do, no error
