"""An MLflow tracker that batches its writes and spools them to disk while the server is unreachable.

Everything the tracker writes is first a *record*, a small JSON-able dict (run creation, params,
metrics, tags, artifact, end). A record is sent at once when the backend answers; when it does
not, the record is appended to `<run_dir>/tracking-spool.jsonl`, and a background thread replays the
spool, in order, at the retry interval until it is empty, while training goes on (later calls and
`flush` replay it too). So a tracking server that goes away costs training nothing but a warning,
and the run catches up when it comes back, whether or not it logs anything more.

Choices worth knowing:
- `mlflow.tracking.MlflowClient` is used explicitly: no global active run, so several trackers
  (a sweep's parent and its children) coexist in one process.
- Unless the user has set them, `orchestrator.tracking.spool` sets `MLFLOW_HTTP_REQUEST_MAX_RETRIES=0`
  and `MLFLOW_HTTP_REQUEST_TIMEOUT=3` for the process when imported: MLflow's defaults (7 retries with
  exponential backoff, 120 s timeout) would stall training for minutes on a dead server. A refused
  connection now fails in milliseconds, a silent host in about 3 s; after a failure the training
  thread spools without trying, and the background thread retries every `retry_interval_s` seconds,
  so a silent host costs training one timeout per outage (`flush()` and `close()` always try). The
  spool, the sender, its background thread and how errors are sorted (a refusal is dropped, anything
  else spooled) are in `orchestrator.tracking.spool`.
- Resuming a run (`run_id=`) skips params already logged with the same value; MLflow refuses to
  change a param's value, so a changed value is logged as a warning and skipped.
- A run that cannot be created at start (server down) is created when the server answers again;
  until then `run_id` is None and the records carry a placeholder that the replay resolves.
- Artifacts that cannot be uploaded stay where they are and only their path is spooled; a file
  that has gone by replay time is reported and skipped. `log_dict`/`log_figure` write their files
  under `<run_dir>/tracking-artifacts/` and delete them once uploaded.
- Artifacts have their own timeout (`artifact_timeout_s`) and, when they fail, a spool of their own, so that a
  slow artifact store never holds up the run's metrics or its end (see `orchestrator.tracking.spool`).
- The tracker writes no credential of its store: `hide` masks the URI's password in every log record; the run
  name, param and tag values and the text of `log_dict`/`log_text` pass through `scrub`; an HTTP server's user
  and password go to MLflow through its environment variables (`credentials_to_env`), and `uri` is without them.
- Every file submitted is listed with its SHA-256 (`orchestrator.tracking.manifest`); a run that ends FINISHED
  uploads the list last (`artifacts.sha256.json`) and then, behind every upload still spooled, sets the tag
  `artifacts_sha256`: what a stage needs to be reused.
- A new run is recorded as the user an authenticated server knows this process as (`mlflow.user`), so that
  `orchestrator.stages` can tell this user's runs from others'; elsewhere as the machine's login name.
- One live tracker per run directory: the spool is guarded by a lock within the process only.
"""

from __future__ import annotations

import getpass
import logging
import threading
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from orchestrator.tracking.base import (
    EXPERIMENT_TAGS,
    RunLogger,
    dump_text,
    store_artifacts,
    truncate,
)
from orchestrator.tracking.identity import whoami
from orchestrator.tracking.manifest import MANIFEST_FILE, Manifest, text_digest
from orchestrator.tracking.spool import (  # sets MLflow's client defaults before mlflow is imported
    ARTIFACT_DIR,
    METRICS_PER_BATCH,
    PARAMS_PER_BATCH,
    PENDING,
    TAGS_PER_BATCH,
    Sender,
    Spool,
    refused,
)
from orchestrator.tracking.uri import credentials_to_env, embedded_uri, hide, redact, scrub

__all__ = ["EXPERIMENT_TAGS", "MlflowLogger", "Sender", "Spool", "replay_spool", "store_artifacts"]

log = logging.getLogger(__name__)

SPOOL_FILE = "tracking-spool.jsonl"
MAX_TAG_VALUE_LENGTH = 8000  # mlflow.utils.validation.MAX_TAG_VAL_LENGTH


def _now_ms() -> int:
    return int(time.time() * 1000)


def run_user(uri: str) -> str:
    """Who a new run is recorded as (`mlflow.user`, the run's user): the user an authenticated server knows this
    process as (what `orchestrator.stages` trusts), else this machine's login name."""
    who = whoami(uri)
    if who is not None:
        return who.user
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no login name for this uid (a container's)
        return "unknown"


class MlflowLogger(RunLogger):
    """A `RunLogger` writing to MLflow through `MlflowClient`, spooling to disk while the backend is away.

    Args:
        uri: tracking URI used as is (`http://127.0.0.1:5000`, `sqlite:///…`); None: the embedded
            store `sqlite:///<run_dir>/mlflow.db` with artifacts under `<run_dir>/mlartifacts`.
        experiment: experiment name, created when missing (restored when deleted).
        run_name: display name of a new run.
        run_id: continue this run (status set back to RUNNING) instead of starting one.
        parent_run_id: make the new run a child of this one (tag `mlflow.parentRunId`).
        tags: tags of a new run, or set on the resumed one.
        run_dir: directory of the embedded store, the spool and pending artifacts.
        flush_every: `log_metrics` calls buffered before one batched send (1: send each call).
        retry_interval_s: after a failed send, spool without trying for this long; the background thread
            retries at this interval (without it, the wait doubles with each further failure, up to a minute).
        background: replay the spool from a daemon thread while it holds anything (stopped by `close`).
        artifact_timeout_s: seconds an artifact upload may wait on the store, per request.
        artifact_tries: uploads in a row that time out before no more are tried (the files wait in the spool).
    """

    def __init__(
        self,
        uri: str | None,
        experiment: str,
        run_name: str | None = None,
        run_id: str | None = None,
        parent_run_id: str | None = None,
        tags: Mapping[str, Any] | None = None,
        run_dir: Path = Path("."),
        flush_every: int = 1,
        retry_interval_s: float = 5.0,
        background: bool = True,
        artifact_timeout_s: int = 60,
        artifact_tries: int = 3,
    ):
        if flush_every < 1:
            raise ValueError(f"flush_every must be at least 1, got {flush_every}")
        self.run_dir = Path(run_dir).resolve()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        hide(uri)
        self.uri = credentials_to_env(uri or embedded_uri(self.run_dir))
        self.flush_every = flush_every
        self._sender = Sender(
            self.uri,
            self.run_dir / SPOOL_FILE,
            retry_interval_s,
            background=background,
            artifact_timeout_s=artifact_timeout_s,
            artifact_tries=artifact_tries,
        )
        self._lock = threading.RLock()  # the buffer, params and state; the sender has its own locks
        self._buffer: list[list] = []  # [key, value, timestamp_ms, step]
        self._buffered_calls = 0
        self._params: dict[str, str] = {}  # params known to be logged in this run
        self._closed = False
        tags = {str(k): truncate(scrub(str(v)), MAX_TAG_VALUE_LENGTH) for k, v in (tags or {}).items()}
        if run_id is not None and self._resume(run_id):
            self.manifest = Manifest(self.run_dir, resumed=True)
            self._key = run_id
            self._sender.submit({"op": "resume", "run": run_id})
            if tags:
                self.set_tags(tags)
            return
        self.manifest = Manifest(self.run_dir, resumed=False)
        self._key = f"{PENDING}{uuid.uuid4().hex}"
        if parent_run_id is not None:
            tags["mlflow.parentRunId"] = parent_run_id
        tags.setdefault("mlflow.user", run_user(self.uri))
        artifacts = (self.run_dir / "mlartifacts").as_uri() if uri is None else store_artifacts(uri)
        run_name = None if run_name is None else scrub(run_name)  # a run name made from the overrides
        create = {"experiment": experiment, "artifact_location": artifacts, "run_name": run_name, "tags": tags}
        self._sender.submit({"op": "create", "run": self._key, "start_time": _now_ms(), **create})

    # ---------------------------------------------------------------- the RunLogger interface

    @property
    def run_id(self) -> str | None:
        """The MLflow run id; None while the run waits in the spool to be created."""
        return self._sender.ids.get(self._key) if self._key.startswith(PENDING) else self._key

    def log_params(self, params: Mapping[str, Any]) -> None:
        with self._lock:
            new = {}
            for key, value in params.items():
                key, value = str(key), truncate(scrub(str(value)))
                old = self._params.get(key)
                if old is None:
                    new[key] = self._params[key] = value
                elif old != value:
                    log.warning("param %r was logged as %r; MLflow cannot change it to %r: skipped", key, old, value)
            items = list(new.items())
            for i in range(0, len(items), PARAMS_PER_BATCH):
                self._submit("params", dict(items[i : i + PARAMS_PER_BATCH]))

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        with self._lock:
            ts = _now_ms()
            self._buffer.extend([str(k), float(v), ts, int(step)] for k, v in metrics.items())
            self._buffered_calls += 1
            if self._buffered_calls >= self.flush_every:
                self._send_buffer()

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        items = [(str(k), truncate(scrub(str(v)), MAX_TAG_VALUE_LENGTH)) for k, v in tags.items()]
        with self._lock:
            for i in range(0, len(items), TAGS_PER_BATCH):
                self._submit("tags", dict(items[i : i + TAGS_PER_BATCH]))

    def log_artifact(self, local_path: str | Path, artifact_path: str | None = None) -> None:
        self._submit_artifact(Path(local_path).resolve(), artifact_path, owned=False)

    def delete_artifact(self, artifact_path: str) -> None:
        """Delete `artifact_path` from the run's artifacts, after the records submitted before (spooled alike)."""
        with self._lock:
            self.manifest.remove(artifact_path)
            self._submit("delete", artifact_path)

    def log_dict(self, obj: Any, artifact_file: str) -> None:
        self.log_text(dump_text(obj, artifact_file), artifact_file)

    def log_text(self, text: str, artifact_file: str) -> None:
        path = self._owned_file(artifact_file)
        path.write_text(scrub(text))
        self._submit_owned(path, artifact_file)

    def log_figure(self, fig: Any, artifact_file: str) -> None:
        path = self._owned_file(artifact_file)
        fig.savefig(path)
        self._submit_owned(path, artifact_file)

    def flush(self) -> None:
        """Try now to send the spool and the buffered metrics, even within the retry interval."""
        with self._lock:
            self._sender.drain(force=True)
            self._send_buffer()

    def close(self, status: str = "FINISHED") -> None:
        """Flush, set the run's terminal status (spooled with the rest if the backend is away) and stop
        the background thread."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if status == "FINISHED":
                text = self.manifest.text()
                path = self._owned_file(MANIFEST_FILE)
                path.write_text(text)
                self._sender.submit({"op": "artifact", "run": self._key, "path": str(path), "owned": True})
                self._sender.submit({"op": "complete", "run": self._key, "complete": text_digest(text)})
            self.flush()
            self._sender.submit({"op": "end", "run": self._key, "status": status, "end_time": _now_ms()})
        self._sender.stop()
        if self._sender.artifacts.count:
            log.warning(
                "tracking: %d artifact uploads of this run wait in %s: the run is not complete in the store (as a "
                "stage it is not reused) until they land",
                self._sender.artifacts.count,
                self._sender.artifacts.path.name,
            )
        if self.pending():
            log.warning(
                "tracking: %d records left in %s and %s; the next tracker on this run directory sends them, "
                "or orchestrator.tracking.mlflow.replay_spool(%r, %r)",
                self.pending(),
                self._sender.spool.path.name,
                self._sender.artifacts.path.name,
                str(self.run_dir),
                redact(self.uri),
            )

    def pending(self) -> int:
        """Records waiting in the spool file (metrics buffered in memory are not counted)."""
        return self._sender.pending()

    # ---------------------------------------------------------------- helpers

    def _resume(self, run_id: str) -> bool:
        """Learn the resumed run's params; False if the backend says the run does not exist."""
        try:
            self._params = dict(self._sender.client.get_run(run_id).data.params)
        except Exception as err:
            if refused(err):
                log.warning("tracking: run %s cannot be resumed (%s); starting a new run", run_id, err)
                return False
            # Unknown until the server is back: params are sent again, which MLflow accepts when unchanged.
            self._sender.note_failure(err)
        return True

    def _submit(self, op: str, entries: Any) -> None:
        self._sender.submit({"op": op, "run": self._key, op: entries})

    def _send_buffer(self) -> None:
        buffer, self._buffer, self._buffered_calls = self._buffer, [], 0
        for i in range(0, len(buffer), METRICS_PER_BATCH):
            self._submit("metrics", buffer[i : i + METRICS_PER_BATCH])

    def _owned_file(self, artifact_file: str) -> Path:
        folder = self.run_dir / ARTIFACT_DIR / uuid.uuid4().hex
        folder.mkdir(parents=True)
        return folder / Path(artifact_file).name

    def _submit_owned(self, path: Path, artifact_file: str) -> None:
        parent = Path(artifact_file).parent.as_posix()
        self._submit_artifact(path, None if parent in ("", ".") else parent, owned=True)

    def _submit_artifact(self, path: Path, artifact_path: str | None, owned: bool) -> None:
        """`owned`: a file the tracker wrote itself, deleted once uploaded."""
        with self._lock:
            self.manifest.add(path, artifact_path)
        record = {"op": "artifact", "run": self._key, "path": str(path), "artifact_path": artifact_path}
        self._sender.submit({**record, "owned": owned})


def replay_spool(run_dir: str | Path, uri: str | None) -> int:
    """Send what an ended tracker left in `<run_dir>/tracking-spool.jsonl`; return the records still left.

    `uri` None means the run directory's embedded store. Runs that tracker could not create are created now.
    """
    sender = Sender(uri or embedded_uri(run_dir), Path(run_dir) / SPOOL_FILE, retry_interval_s=0.0)
    sender.drain(force=True)
    return sender.pending()
