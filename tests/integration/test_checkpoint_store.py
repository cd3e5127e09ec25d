"""Old checkpoints leave a real tracking server's artifact store (it proxies artifacts), whether the deletes are
sent at once or spooled while the server is down and replayed, in order, once it answers."""

from __future__ import annotations

import pytest
from mlflow.tracking import MlflowClient

from orchestrator import checkpoint
from orchestrator.tracking.mlflow import MlflowLogger
from orchestrator.tracking.server import free_port, start_local_server

pytestmark = pytest.mark.slow  # a server takes a few seconds to start


def save_and_prune(logger: MlflowLogger, ckpts, iterations) -> None:
    """As Trainer.save: write, upload, then keep the newest two, here and in the store."""
    for i in iterations:
        logger.log_artifact(checkpoint.save(ckpts, i, {"w": i}), "checkpoints")
        checkpoint.prune(ckpts, keep=2, forget=lambda old: logger.delete_artifact(f"checkpoints/{old.name}"))


def test_pruned_checkpoints_leave_a_tracking_servers_store_also_after_an_outage(tmp_path):
    port = free_port()
    run_dir = tmp_path / "run"
    ckpts = run_dir / "checkpoints"
    logger = MlflowLogger(f"http://127.0.0.1:{port}", "default", run_dir=run_dir, retry_interval_s=60)
    save_and_prune(logger, ckpts, range(1, 5))  # the server is down: everything spooled
    assert logger.run_id is None and logger.pending() > 0

    with start_local_server(f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "artifacts", port=port) as server:
        logger.flush()
        assert logger.pending() == 0
        client = MlflowClient(server.uri)

        def stored() -> list[str]:
            return sorted(a.path for a in client.list_artifacts(logger.run_id, "checkpoints"))

        # Checkpoints 1 and 2 were deleted here before the server came back: their uploads were dropped,
        # their deletes found nothing to delete.
        assert stored() == ["checkpoints/ckpt-0000003.pt", "checkpoints/ckpt-0000004.pt"]
        save_and_prune(logger, ckpts, [5, 6])  # sent at once now
        assert stored() == ["checkpoints/ckpt-0000005.pt", "checkpoints/ckpt-0000006.pt"]
        assert sorted(p.name for p in (tmp_path / "artifacts").rglob("ckpt-*.pt")) == [
            "ckpt-0000005.pt",
            "ckpt-0000006.pt",
        ]
        logger.close()
