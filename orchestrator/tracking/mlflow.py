"""An MLflow tracker that batches its writes and spools them to disk while the server is unreachable.

Everything the tracker writes is first a *record*, a small JSON-able dict (run creation, params,
metrics, tags, artifact, end). A record is sent at once when the backend answers; when it does
not, the record is appended to `<run_dir>/tracking-spool.jsonl`, and later calls replay the spool,
in order, before sending anything new. So a tracking server that goes away costs training nothing
but a warning, and the run catches up when it comes back.

Choices worth knowing:
- `mlflow.tracking.MlflowClient` is used explicitly: no global active run, so several trackers
  (a sweep's parent and its children) coexist in one process.
- Unless the user has set them, this module sets `MLFLOW_HTTP_REQUEST_MAX_RETRIES=0` and
  `MLFLOW_HTTP_REQUEST_TIMEOUT=3` for the process when imported: MLflow's defaults (7 retries with
  exponential backoff, 120 s timeout) would stall training for minutes on a dead server. A refused
  connection now fails in milliseconds, a silent host in about 3 s; after a failure the tracker
  spools without trying for `retry_interval_s` seconds, doubling with each further failure up to
  a minute, so a silent host stalls training for 3 s a minute at most (`flush()` and `close()`
  always try).
- Errors are sorted in two kinds. MLflow's refusals (invalid value, changed param, unknown run)
  would fail again on every replay, so they are logged and the offending entries dropped (a
  refused batch is retried entry by entry, so one bad key does not lose the other 99). Anything
  else (connection refused, timeouts, 5xx, a locked SQLite file) spools the record.
- Resuming a run (`run_id=`) skips params already logged with the same value; MLflow refuses to
  change a param's value, so a changed value is logged as a warning and skipped.
- A run that cannot be created at start (server down) is created when the server answers again;
  until then `run_id` is None and the records carry a placeholder that the replay resolves.
- Artifacts that cannot be uploaded stay where they are and only their path is spooled; a file
  that has gone by replay time is reported and skipped. `log_dict`/`log_figure` write their files
  under `<run_dir>/tracking-artifacts/` and delete them once uploaded.
- One live tracker per run directory: the spool is guarded by a lock within the process only.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import time
import uuid
from collections import deque
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

# No calls home from training jobs (MLflow 3 sends client telemetry unless told not to).
os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "3")
os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # a bar per downloaded stage artifact

from mlflow.entities import Metric, Param, RunTag  # noqa: E402 - after the environment defaults
from mlflow.exceptions import MlflowException  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from orchestrator.tracking.base import (  # noqa: E402 - stores' URIs live in base, re-exported here
    EXPERIMENT_TAGS,
    Tracker,
    dump_text,
    embedded_uri,
    store_artifacts,
    truncate,
)

log = logging.getLogger(__name__)

SPOOL_FILE = "tracking-spool.jsonl"
ARTIFACT_DIR = "tracking-artifacts"
MAX_TAG_VALUE_LENGTH = 8000  # mlflow.utils.validation.MAX_TAG_VAL_LENGTH
PARAMS_PER_BATCH = 100  # MLflow's per-request limits
TAGS_PER_BATCH = 100
METRICS_PER_BATCH = 1000
PENDING = "pending-"  # prefix of a run key whose run is not created yet
# MLflow error codes that a retry cannot fix: the entries are dropped rather than spooled.
REFUSALS = {"INVALID_PARAMETER_VALUE", "RESOURCE_ALREADY_EXISTS", "RESOURCE_DOES_NOT_EXIST", "BAD_REQUEST"}
_SPOOL_LOCKS: dict[Path, threading.RLock] = {}


class Refused(Exception):
    """A record the backend will never accept (see REFUSALS)."""


def _refused(err: BaseException) -> bool:
    """True for errors a retry cannot fix: MLflow's refusals, and a malformed record (KeyError, TypeError)."""
    if isinstance(err, MlflowException):
        return err.error_code in REFUSALS
    return isinstance(err, Refused | KeyError | TypeError)


def _now_ms() -> int:
    return int(time.time() * 1000)


class Spool:
    """An append-only JSON-lines file of records that could not be sent, oldest first."""

    def __init__(self, path: Path):
        self.path = path
        self.lock = _SPOOL_LOCKS.setdefault(path.resolve(), threading.RLock())
        self.count = sum(1 for line in path.open() if line.strip()) if path.exists() else 0

    def append(self, records: Iterable[dict]) -> None:
        lines = [json.dumps(r) + "\n" for r in records]
        if lines:
            with self.path.open("a") as f:
                f.writelines(lines)
                f.flush()
                os.fsync(f.fileno())
            self.count += len(lines)

    def read(self) -> list[dict]:
        """The spooled records; a line that does not parse (a write cut short by a crash) is skipped."""
        if not self.path.exists():
            return []
        records = []
        for number, line in enumerate(self.path.read_text().splitlines(), 1):
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                record = None
            if isinstance(record, dict) and "op" in record and "run" in record:
                records.append(record)
            elif line.strip():
                log.warning("tracking: %s line %d is not a record; skipped", self.path, number)
        return records

    def replace(self, records: list[dict]) -> None:
        """Make `records` the whole spool (atomically); an empty list deletes the file."""
        if not records:
            self.path.unlink(missing_ok=True)
        else:
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text("".join(json.dumps(r) + "\n" for r in records))
            os.replace(tmp, self.path)
        self.count = len(records)


class Sender:
    """Sends records to one MLflow backend, in order, spooling them while it fails.

    `submit` sends a record at once when the spool is empty (or can be emptied first), and
    otherwise appends it; `drain` replays the spool. Runs created from a spooled `create` record
    get their id in `ids` (placeholder key -> run id).
    """

    def __init__(self, uri: str, spool_path: Path, retry_interval_s: float, max_retry_interval_s: float = 60.0):
        self.uri = uri
        self.retry_interval_s = retry_interval_s
        self.max_retry_interval_s = max_retry_interval_s
        self.client = MlflowClient(tracking_uri=uri)
        self.spool = Spool(spool_path)
        self.lock = self.spool.lock
        self.ids: dict[str, str] = {}
        self._retry_at = 0.0  # time.monotonic() before which no send is tried
        self._failures = 0  # consecutive failed attempts

    def submit(self, record: dict) -> None:
        """Send `record` now, or append it to the spool if the backend is (or recently was) away.

        Never raises: a record that can be neither sent nor spooled (disk full) is logged and lost.
        """
        with self.lock:
            try:
                if (self.spool.count and not self.drain()) or time.monotonic() < self._retry_at:
                    self.spool.append([record])
                else:
                    self.spool.append(self._process(deque([record])))
            except Exception as err:
                log.error("tracking: a %s record was lost: %s", record["op"], err)

    def drain(self, force: bool = False) -> bool:
        """Replay the spool in order (`force`: even within the retry interval); True when it is empty."""
        with self.lock:
            if not self.spool.count:
                return True
            if not force and time.monotonic() < self._retry_at:
                return False
            records = self.spool.read()
            rest = self._process(deque(records))
            if rest != records:
                self.spool.replace([self._resolved(r) for r in rest])
                log.info("tracking: replayed %d spooled records, %d left", len(records) - len(rest), len(rest))
            return not rest

    def note_failure(self, err: BaseException) -> None:
        """Remember that the backend failed: no sends are tried for a while, doubling with each failure
        from `retry_interval_s` to `max_retry_interval_s` (a silent host costs a timeout per attempt)."""
        self._failures += 1
        wait = min(self.retry_interval_s * 2 ** (self._failures - 1), self.max_retry_interval_s)
        self._retry_at = time.monotonic() + wait
        if self._failures == 1:
            log.warning("tracking: %s unreachable (%s); spooling to %s", self.uri, err, self.spool.path)

    def _process(self, queue: deque[dict]) -> list[dict]:
        """Send records from the front of `queue` until it is empty or the backend fails; return the rest."""
        while queue:
            batch, used = _merge_metrics(queue)
            try:
                self._send(batch)
            except Exception as err:
                if not _refused(err):
                    self.note_failure(err)
                    return list(queue)
                for _ in range(used):
                    queue.popleft()
                singles = _split(batch)
                if len(singles) > 1:  # retry entry by entry, dropping only the refused ones
                    queue.extendleft(reversed(singles))
                else:
                    log.warning("tracking: %s record dropped, refused by MLflow: %s", batch["op"], err)
                    _discard_owned(batch)
                continue
            for _ in range(used):
                queue.popleft()
            _discard_owned(batch)
            if self._failures:
                self._failures, self._retry_at = 0, 0.0
                log.warning("tracking: %s answers again", self.uri)
        return []

    def _resolved(self, record: dict) -> dict:
        """`record` with its placeholder run key replaced by the run id, once the run exists."""
        run = self.ids.get(record["run"])
        return record if run is None else {**record, "run": run}

    def _run(self, record: dict) -> str:
        run = record["run"]
        if run.startswith(PENDING):
            if run not in self.ids:
                raise Refused(f"run {run} was never created")
            run = self.ids[run]
        return run

    def _send(self, record: dict) -> None:
        """One request (up to three for run creation) to the backend; raises on any failure."""
        op, client = record["op"], self.client
        if op == "create":
            self._create(record)
        elif op == "resume":
            client.update_run(record["run"], status="RUNNING")
        elif op == "params":
            params = [Param(k, v) for k, v in record["params"].items()]
            client.log_batch(self._run(record), params=params, synchronous=True)
        elif op == "metrics":
            metrics = [Metric(k, v, ts, step) for k, v, ts, step in record["metrics"]]
            client.log_batch(self._run(record), metrics=metrics, synchronous=True)
        elif op == "tags":
            tags = [RunTag(k, v) for k, v in record["tags"].items()]
            client.log_batch(self._run(record), tags=tags, synchronous=True)
        elif op == "artifact":
            path = Path(record["path"])
            if not path.exists():
                raise Refused(f"artifact {path} no longer exists")
            upload = client.log_artifacts if path.is_dir() else client.log_artifact
            upload(self._run(record), str(path), record.get("artifact_path"))
        elif op == "end":
            client.set_terminated(self._run(record), status=record["status"], end_time=record["end_time"])
        else:
            raise Refused(f"unknown record {op!r}")

    def _create(self, record: dict) -> None:
        client, name = self.client, record["experiment"]
        experiment = client.get_experiment_by_name(name)
        if experiment is None:
            try:
                experiment_id = client.create_experiment(
                    name, artifact_location=record["artifact_location"], tags=EXPERIMENT_TAGS
                )
            except MlflowException as err:  # created meanwhile by a parallel job
                if err.error_code != "RESOURCE_ALREADY_EXISTS":
                    raise
                experiment_id = client.get_experiment_by_name(name).experiment_id
        else:
            experiment_id = experiment.experiment_id
            if experiment.lifecycle_stage == "deleted":
                log.warning("tracking: experiment %r was deleted; restoring it", name)
                client.restore_experiment(experiment_id)
            for key, value in EXPERIMENT_TAGS.items():
                if key not in experiment.tags:
                    client.set_experiment_tag(experiment_id, key, value)
        tags, run_name = record["tags"], record["run_name"]
        run = client.create_run(experiment_id, start_time=record["start_time"], tags=tags, run_name=run_name)
        self.ids[record["run"]] = run.info.run_id


class MlflowTracker(Tracker):
    """A `Tracker` writing to MLflow through `MlflowClient`, spooling to disk while the backend is away.

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
        retry_interval_s: after a failed send, spool without trying for this long (doubling with each
            further failure, up to a minute).
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
    ):
        if flush_every < 1:
            raise ValueError(f"flush_every must be at least 1, got {flush_every}")
        self.run_dir = Path(run_dir).resolve()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.uri = uri or embedded_uri(self.run_dir)
        self.flush_every = flush_every
        self._sender = Sender(self.uri, self.run_dir / SPOOL_FILE, retry_interval_s)
        self._lock = self._sender.lock
        self._buffer: list[list] = []  # [key, value, timestamp_ms, step]
        self._buffered_calls = 0
        self._params: dict[str, str] = {}  # params known to be logged in this run
        self._closed = False
        tags = {str(k): truncate(str(v), MAX_TAG_VALUE_LENGTH) for k, v in (tags or {}).items()}
        if run_id is not None and self._resume(run_id):
            self._key = run_id
            self._sender.submit({"op": "resume", "run": run_id})
            if tags:
                self.set_tags(tags)
            return
        self._key = f"{PENDING}{uuid.uuid4().hex}"
        if parent_run_id is not None:
            tags["mlflow.parentRunId"] = parent_run_id
        artifacts = (self.run_dir / "mlartifacts").as_uri() if uri is None else store_artifacts(uri)
        create = {"experiment": experiment, "artifact_location": artifacts, "run_name": run_name, "tags": tags}
        self._sender.submit({"op": "create", "run": self._key, "start_time": _now_ms(), **create})

    # ---------------------------------------------------------------- the Tracker interface

    @property
    def run_id(self) -> str | None:
        """The MLflow run id; None while the run waits in the spool to be created."""
        return self._sender.ids.get(self._key) if self._key.startswith(PENDING) else self._key

    def log_params(self, params: Mapping[str, Any]) -> None:
        with self._lock:
            new = {}
            for key, value in params.items():
                key, value = str(key), truncate(str(value))
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
        items = [(str(k), truncate(str(v), MAX_TAG_VALUE_LENGTH)) for k, v in tags.items()]
        with self._lock:
            for i in range(0, len(items), TAGS_PER_BATCH):
                self._submit("tags", dict(items[i : i + TAGS_PER_BATCH]))

    def log_artifact(self, local_path: str | Path, artifact_path: str | None = None) -> None:
        self._submit_artifact(Path(local_path).resolve(), artifact_path, owned=False)

    def log_dict(self, obj: Any, artifact_file: str) -> None:
        path = self._owned_file(artifact_file)
        path.write_text(dump_text(obj, artifact_file))
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
        """Flush and set the run's terminal status (spooled with the rest if the backend is away)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self.flush()
            self._sender.submit({"op": "end", "run": self._key, "status": status, "end_time": _now_ms()})
            if self.pending():
                log.warning(
                    "tracking: %d records left in %s; the next tracker on this run directory sends them, "
                    "or orchestrator.tracking.mlflow.replay_spool(%r, %r)",
                    self.pending(),
                    self._sender.spool.path,
                    str(self.run_dir),
                    self.uri,
                )

    def pending(self) -> int:
        """Records waiting in the spool file (metrics buffered in memory are not counted)."""
        return self._sender.spool.count

    # ---------------------------------------------------------------- helpers

    def _resume(self, run_id: str) -> bool:
        """Learn the resumed run's params; False if the backend says the run does not exist."""
        try:
            self._params = dict(self._sender.client.get_run(run_id).data.params)
        except Exception as err:
            if _refused(err):
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
        record = {"op": "artifact", "run": self._key, "path": str(path), "artifact_path": artifact_path}
        self._sender.submit({**record, "owned": owned})


def replay_spool(run_dir: str | Path, uri: str | None) -> int:
    """Send what an ended tracker left in `<run_dir>/tracking-spool.jsonl`; return the records still left.

    `uri` None means the run directory's embedded store. Runs that tracker could not create are created now.
    """
    sender = Sender(uri or embedded_uri(run_dir), Path(run_dir) / SPOOL_FILE, retry_interval_s=0.0)
    sender.drain(force=True)
    return sender.spool.count


def _merge_metrics(queue: deque[dict]) -> tuple[dict, int]:
    """The front record, merged with the metric records right behind it (same run, one batch's worth)."""
    first = queue[0]
    if first["op"] != "metrics" or first.get("single"):
        return first, 1
    metrics, used = list(first["metrics"]), 1
    while used < len(queue):
        nxt = queue[used]
        if nxt["op"] != "metrics" or nxt["run"] != first["run"] or nxt.get("single"):
            break
        if len(metrics) + len(nxt["metrics"]) > METRICS_PER_BATCH:
            break
        metrics += nxt["metrics"]
        used += 1
    return {**first, "metrics": metrics}, used


def _split(record: dict) -> list[dict]:
    """A params/metrics/tags record as one record per entry, marked not to be merged again (others: itself)."""
    op = record["op"]
    if op == "metrics":
        return [{**record, "metrics": [m], "single": True} for m in record["metrics"]]
    if op in ("params", "tags"):
        return [{**record, op: {k: v}, "single": True} for k, v in record[op].items()]
    return [record]


def _discard_owned(record: dict) -> None:
    """Delete a file the tracker wrote for upload (log_dict, log_figure) once it is done with."""
    if record["op"] == "artifact" and record.get("owned"):
        shutil.rmtree(Path(record["path"]).parent, ignore_errors=True)
