"""An artifact store that stalls does not hold up the run's metrics or its end: uploads have their own timeout and
a bounded number of tries, then wait in the run directory's spool for `replay_spool` (a real SQLite tracking store,
its experiment's artifacts on a local HTTP address that first stalls, then answers)."""

from __future__ import annotations

import hashlib
import json
import os
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from mlflow.tracking import MlflowClient

from orchestrator.tracking.mlflow import MlflowLogger, replay_spool
from orchestrator.tracking.spool import artifact_timeout


def stalling_listener() -> socket.socket:
    """A socket on 127.0.0.1 that takes connections (the kernel completes them) and never reads or answers."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)
    return sock


class ArtifactStore(ThreadingHTTPServer):
    """Stores what is PUT to it, path -> bytes (MLflow's HTTP artifact repository uploads by PUT)."""

    def __init__(self, port: int):
        self.files: dict[str, bytes] = {}
        store = self

        class Handler(BaseHTTPRequestHandler):
            def do_PUT(self):
                store.files[self.path] = self.rfile.read(int(self.headers["Content-Length"]))
                self.send_response(200)
                self.end_headers()

            def log_message(self, *args):
                pass

        super().__init__(("127.0.0.1", port), Handler)


def test_a_stalling_artifact_store_does_not_hold_up_the_run_end_and_its_files_are_sent_later(tmp_path):
    listener = stalling_listener()
    port = listener.getsockname()[1]
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    MlflowClient(uri).create_experiment("slow", artifact_location=f"http://127.0.0.1:{port}/artifacts")
    run_dir = tmp_path / "run"
    small = tmp_path / "config.json"
    small.write_text('{"a": 1}')
    big = tmp_path / "ckpt.pt"  # larger than the socket buffers: the upload itself stalls, not only the answer
    big.write_bytes(os.urandom(24 * 2**20))

    tracker = MlflowLogger(
        uri, "slow", run_dir=run_dir, retry_interval_s=0.5, artifact_timeout_s=1, artifact_tries=2
    )  # fmt: skip

    def the_run() -> None:
        tracker.log_metrics({"loss": 1.0}, step=1)
        tracker.log_artifact(small)  # times out after 1 s, then waits aside
        tracker.log_dict({"b": 2}, "eval/summary.json")
        tracker.log_artifact(big, "checkpoints")
        tracker.log_metrics({"loss": 0.5}, step=2)
        tracker.close()

    started = time.monotonic()
    thread = threading.Thread(target=the_run, daemon=True)  # a hang fails the test instead of stopping it
    thread.start()
    thread.join(60)
    elapsed = time.monotonic() - started
    assert not thread.is_alive(), "the run's end hung on the artifact store"
    # Two tries of at most 1 s each (and the requests' own connection), not a hang and not a retry per interval.
    assert elapsed < 10, elapsed
    run = MlflowClient(uri).get_run(tracker.run_id)
    assert run.info.status == "FINISHED"  # the end was not queued behind the files
    assert [m.value for m in MlflowClient(uri).get_metric_history(tracker.run_id, "loss")] == [1.0, 0.5]
    assert tracker.pending() == 5  # the three files, the manifest and the completion tag, in the side spool
    assert "artifacts_sha256" not in run.data.tags  # FINISHED, but not complete: as a stage it is not reused
    assert (run_dir / "tracking-spool-artifacts.jsonl").exists() and not (run_dir / "tracking-spool.jsonl").exists()
    assert small.exists() and big.exists()

    listener.close()
    with ArtifactStore(port) as store:
        threading.Thread(target=store.serve_forever, daemon=True).start()
        assert replay_spool(run_dir, uri) == 0
        store.shutdown()
    where = f"/artifacts/{tracker.run_id}/artifacts"  # the run's artifact root under the experiment's
    assert store.files[f"{where}/config.json"] == small.read_bytes()
    assert store.files[f"{where}/eval/summary.json"] == b'{\n  "b": 2\n}'
    assert store.files[f"{where}/checkpoints/ckpt.pt"] == big.read_bytes()
    manifest = store.files[f"{where}/artifacts.sha256.json"]
    assert set(json.loads(manifest)) == {"config.json", "eval/summary.json", "checkpoints/ckpt.pt"}
    tags = MlflowClient(uri).get_run(tracker.run_id).data.tags  # set once the files had all landed
    assert tags["artifacts_sha256"] == hashlib.sha256(manifest).hexdigest()
    assert not (run_dir / "tracking-spool-artifacts.jsonl").exists()
    assert not list((run_dir / "tracking-artifacts").iterdir())  # the tracker's own copy, deleted once sent


def test_an_upload_gets_its_own_request_timeout_and_the_others_keep_theirs(monkeypatch):
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "3")
    monkeypatch.delenv("MLFLOW_ARTIFACT_UPLOAD_DOWNLOAD_TIMEOUT", raising=False)
    with artifact_timeout(45):
        assert os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == "45"
        assert os.environ["MLFLOW_ARTIFACT_UPLOAD_DOWNLOAD_TIMEOUT"] == "45"
    assert os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == "3"
    assert "MLFLOW_ARTIFACT_UPLOAD_DOWNLOAD_TIMEOUT" not in os.environ


def test_an_outage_is_not_a_stall_artifacts_wait_for_the_store_without_using_up_their_tries(tmp_path):
    """Nothing listens at the artifact address (connection refused): the uploads are retried, not given up."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    MlflowClient(uri).create_experiment("away", artifact_location=f"http://127.0.0.1:{port}/artifacts")
    tracker = MlflowLogger(uri, "away", run_dir=tmp_path / "run", background=False, artifact_tries=1)
    for i in range(3):
        tracker.log_dict({"i": i}, f"f{i}.json")
        tracker.flush()
    sender = tracker._sender
    assert not sender.artifacts_given_up() and tracker.pending() == 3
    tracker.close()
    assert MlflowClient(uri).get_run(tracker.run_id).info.status == "FINISHED"
    assert Path(tmp_path / "run" / "tracking-spool-artifacts.jsonl").exists()
