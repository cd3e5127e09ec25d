"""The disk spool of the MLflow tracker and the sender that drains it, in the foreground and in the background.

A `Sender` sends *records* (small JSON-able dicts: run creation, params, metrics, tags, artifact,
end) to one MLflow backend, in order. A record that cannot be sent goes to a `Spool`, an
append-only JSON-lines file, and everything after it follows it there until the spool is drained.

Draining happens three ways: when the sender was made with `background=True`, from a daemon thread
(started when something is first spooled) that retries every `retry_interval_s` for as long as anything is
spooled, so that a run that logs rarely, or has stopped logging, catches up once the server is back;
without it, inline, when a record is submitted after the retry interval (doubled with each failure, up
to `max_retry_interval_s`) has passed; and always on `drain(force=True)` (the tracker's `flush` and
`close`). With the thread, the training thread makes no request while anything is spooled, so a silent
host costs it one timeout per outage, the first failed send.

Locks, always taken in this order: `send_lock` (one sender, not reentrant) serialises the requests to the
backend, so that records arrive in order and the client is used by one thread at a time; `spool.lock`
(one per spool file in the process) guards the file and its count for the few microseconds of an append,
read or rewrite. Requests are made without holding `spool.lock`: while the background thread replays the
spool, training appends to it without waiting for the server.

Errors are sorted in two kinds. MLflow's refusals (invalid value, changed param, unknown run) would
fail again on every replay, so they are logged and the offending entries dropped (a refused batch is
retried entry by entry, so one bad key does not lose the other 99). Anything else (connection
refused, timeouts, 5xx, a locked SQLite file) spools the record.

Artifacts are uploads of any size, often to a store other than the tracking server's (S3, a proxy), so
they go their own way. Each upload may take `artifact_timeout_s` per request (the 3 s of the small requests
would cut an 87 MB checkpoint short on a slow link). An artifact that fails goes to a spool of its own,
`<spool>-artifacts.jsonl`, and the records behind it go on: the run's metrics and its end never wait for its
files. The background thread retries that spool at the retry interval once the main spool is empty; after
`artifact_tries` uploads in a row time out (a store that stalls), this sender tries no more, and the files
wait there for `replay_spool` (or the next tracker on the run directory). A refused connection is an outage,
not a stall: those are retried like the metrics.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

# No calls home from training jobs (MLflow 3 sends client telemetry unless told not to), and no minutes of
# retries on a dead server (MLflow's defaults: 7 retries with exponential backoff, 120 s timeout).
os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "3")
os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # a bar per downloaded stage artifact

from mlflow.entities import Metric, Param, RunTag  # noqa: E402 - after the environment defaults
from mlflow.exceptions import MlflowException  # noqa: E402
from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from orchestrator.tracking.base import EXPERIMENT_TAGS  # noqa: E402
from orchestrator.tracking.manifest import COMPLETE_TAG  # noqa: E402
from orchestrator.tracking.spoolfile import Spool  # noqa: E402
from orchestrator.tracking.uri import credentials_to_env, redact  # noqa: E402

ARTIFACT_DIR = "tracking-artifacts"  # under the run directory, beside the spool: files the tracker wrote for upload

log = logging.getLogger(__name__)

PARAMS_PER_BATCH = 100  # MLflow's per-request limits
TAGS_PER_BATCH = 100
METRICS_PER_BATCH = 1000
PENDING = "pending-"  # prefix of a run key whose run is not created yet
# MLflow error codes that a retry cannot fix: the entries are dropped rather than spooled.
REFUSALS = {"INVALID_PARAMETER_VALUE", "RESOURCE_ALREADY_EXISTS", "RESOURCE_DOES_NOT_EXIST", "BAD_REQUEST"}
# MLflow reads its request timeouts from the environment at each request; an upload swaps them in under this lock.
_TIMEOUT_ENV = ("MLFLOW_HTTP_REQUEST_TIMEOUT", "MLFLOW_ARTIFACT_UPLOAD_DOWNLOAD_TIMEOUT")
_TIMEOUT_LOCK = threading.Lock()


class Refused(Exception):
    """A record the backend will never accept (see REFUSALS)."""


def refused(err: BaseException) -> bool:
    """True for errors a retry cannot fix: MLflow's refusals, and a malformed record (KeyError, TypeError)."""
    if isinstance(err, MlflowException):
        return err.error_code in REFUSALS
    return isinstance(err, Refused | KeyError | TypeError)


# The records that wait in the side spool while uploads are held: uploads, and deletions (kept behind them).
# Records that wait behind the uploads in the side spool: a checkpoint's deletion (which may be of a file still
# waiting there) and the completion tag, set only once every artifact before it has landed.
ARTIFACT_OPS = ("artifact", "delete", "complete")


class Sender:
    """Sends records to one MLflow backend, in order, spooling them while it fails.

    `submit` sends a record at once when the spool is empty (or can be emptied first), and otherwise
    appends it; `drain` replays the spool. Runs created from a spooled `create` record get their id
    in `ids` (placeholder key -> run id). With `background`, a daemon thread drains the spool while it
    is not empty (`stop` ends it). Artifacts that fail wait in the side spool `artifacts`, which only the
    background thread and `drain(force=True)` upload (the module's docstring says how long they are tried).
    """

    def __init__(
        self,
        uri: str,
        spool_path: Path,
        retry_interval_s: float,
        max_retry_interval_s: float = 60.0,
        background: bool = False,
        artifact_timeout_s: int = 60,
        artifact_tries: int = 3,
    ):
        self.uri = uri
        self.retry_interval_s = retry_interval_s
        self.max_retry_interval_s = max_retry_interval_s
        self.client = MlflowClient(tracking_uri=credentials_to_env(uri))
        self.spool = Spool(spool_path)
        spool_path = Path(spool_path)
        self.artifacts = Spool(spool_path.with_name(f"{spool_path.stem}-artifacts{spool_path.suffix}"))
        self.artifact_timeout_s = artifact_timeout_s
        self.artifact_tries = artifact_tries
        self._artifact_retry_at = 0.0  # time.monotonic() before which no artifact upload is tried
        self._artifact_timeouts = 0  # uploads in a row that timed out; at artifact_tries, no more are tried
        self._artifact_failing = False  # the last upload failed
        self._uploading = False  # the background thread is uploading the side spool: records go to the spool
        self.owned_root = Path(spool_path).parent / ARTIFACT_DIR  # where the tracker writes files for upload
        self.send_lock = threading.Lock()
        self.ids: dict[str, str] = {}
        self.background = background
        self._retry_at = 0.0  # time.monotonic() before which no send is tried
        self._failures = 0  # consecutive failed attempts
        self._wake = threading.Event()  # something was spooled
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        if self.artifacts.count:  # left by an earlier tracker: uploaded in the background, never inline
            self._wake_thread()

    def submit(self, record: dict) -> None:
        """Send `record` now, or append it to the spool if the backend is (or recently was) away, or the
        spool is being replayed. Never raises: a record that can be neither sent nor spooled (disk full)
        is logged and lost."""
        try:
            if self._thread is None and self.spool.count and time.monotonic() >= self._retry_at:
                with self.send_lock:  # no background thread (yet): replay inline, but no artifact upload
                    self._drain(artifacts=False)
            if self._spooled(record):  # without waiting for a replay in progress
                return
            with self.send_lock:  # free but for a moment: nothing is being replayed
                if not self._spooled(record):
                    self._spool(self._process(deque([record])))
        except Exception as err:
            log.error("tracking: a %s record was lost: %s", record["op"], err)

    def drain(self, force: bool = False) -> bool:
        """Replay the spool in order (`force`: even within the retry interval); True when it is empty."""
        with self.send_lock:
            return self._drain(force)

    def pending(self) -> int:
        """Records in the spool and artifacts in its side spool."""
        with self.spool.lock, self.artifacts.lock:
            return self.spool.count + self.artifacts.count

    def artifacts_given_up(self) -> bool:
        """Whether uploads timed out `artifact_tries` times in a row, so that this sender tries no more."""
        return self._artifact_timeouts >= self.artifact_tries

    def note_failure(self, err: BaseException) -> None:
        """Remember that the backend failed: no sends are tried for `retry_interval_s`, or, without a
        background thread, for longer with each failure, doubling up to `max_retry_interval_s` (a silent
        host costs the training thread a timeout per attempt then)."""
        self._failures += 1
        doubling = 1 if self._thread is not None else 2 ** (self._failures - 1)
        wait = min(self.retry_interval_s * doubling, self.max_retry_interval_s)
        self._retry_at = time.monotonic() + wait
        if self._failures == 1:
            log.warning("tracking: %s unreachable (%s); spooling to %s", redact(self.uri), err, self.spool.path)

    def stop(self, timeout_s: float = 10.0) -> None:
        """End the background thread (after the request it may be making); the spool stays on disk."""
        self._stopped.set()
        self._wake.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("tracking: the spool's background sender did not stop within %.0f s", timeout_s)

    # ---------------------------------------------------------------- under send_lock

    def _drain(self, force: bool = False, artifacts: bool = True) -> bool:
        with self.spool.lock:
            waiting = self.spool.count
            if waiting and not force and time.monotonic() < self._retry_at:
                return False
        if waiting:
            records, size = self.spool.read()
            rest = self._process(deque(records))
            if rest != records or not records:  # (none: every line was damaged) and what was appended meanwhile
                self.spool.replace(rest, read_up_to=size, resolve=self._resolved)
                log.info("tracking: replayed %d spooled records, %d left", len(records) - len(rest), self.spool.count)
        if artifacts and not self.spool.count:
            self._drain_artifacts(force)
        return self.pending() == 0

    def _drain_artifacts(self, force: bool) -> None:
        """Upload the side spool's artifacts in order, up to the first that fails (unless uploads are given up)."""
        with self.artifacts.lock:
            if not self.artifacts.count or self.artifacts_given_up():
                return
            if not force and time.monotonic() < self._artifact_retry_at:
                return
        records, size = self.artifacts.read()
        done = 0
        self._uploading = True
        try:
            done = self._upload_aside(records)
        finally:
            self._uploading = False
        if done or not records:
            self.artifacts.replace(records[done:], read_up_to=size)

    def _upload_aside(self, records: list[dict]) -> int:
        """Upload `records` in order up to the first failure; how many are done with (uploaded or refused)."""
        done = 0
        for record in records:
            try:
                self._send(record)
            except Exception as err:
                if not refused(err):
                    self._artifact_failed(err)
                    break
                log.warning("tracking: artifact %s dropped, refused by MLflow: %s", record.get("path"), err)
            else:
                self._artifact_timeouts, self._artifact_failing = 0, False
            _discard_owned(record, self.owned_root)
            done += 1
        return done

    def _artifact_failed(self, err: BaseException) -> None:
        """Count an upload that timed out, and wait the retry interval before the next one is tried."""
        self._artifact_retry_at = time.monotonic() + self.retry_interval_s
        if _timed_out(err):
            self._artifact_timeouts += 1
        if self._artifact_timeouts == self.artifact_tries:
            log.warning(
                "tracking: %d artifact uploads in a row timed out after %d s (%s); no more are tried, "
                "they wait in %s for orchestrator.tracking.mlflow.replay_spool",
                self._artifact_timeouts, self.artifact_timeout_s, err, self.artifacts.path,
            )  # fmt: skip
        elif not self._artifact_failing:
            log.warning("tracking: an artifact upload failed (%s); artifacts wait in %s", err, self.artifacts.path)
        self._artifact_failing = True

    def _artifacts_held(self) -> bool:
        """Whether a new artifact goes to the side spool untried: others wait there, or uploads are failing."""
        return bool(self.artifacts.count) or self._artifact_retry_at > time.monotonic() or self.artifacts_given_up()

    def _due(self) -> float | None:
        """When (time.monotonic()) a replay is due, 0.0 if now; None if nothing waits (or only given-up artifacts)."""
        now = time.monotonic()
        if self.spool.count:
            at = self._retry_at
        elif self.artifacts.count and not self.artifacts_given_up():
            at = self._artifact_retry_at
        else:
            return None
        return 0.0 if at <= now else at

    def _spooled(self, record: dict) -> bool:
        """Append `record` to the spool if it is not empty, no send is to be tried yet, or the background
        thread is uploading an artifact (which may take `artifact_timeout_s`); True if so."""
        with self.spool.lock:
            if self.spool.count or time.monotonic() < self._retry_at or self._uploading:
                self._spool([record])
                return True
        return False

    def _spool(self, records: list[dict], spool: Spool | None = None) -> None:
        if records:
            (spool or self.spool).append(records)
            self._wake_thread()

    def _wake_thread(self) -> None:
        """Start the background thread (with `background`) or wake it: something was spooled."""
        if self.background and not self._stopped.is_set():
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="tracking-spool", daemon=True)
                self._thread.start()
            self._wake.set()

    def _process(self, queue: deque[dict]) -> list[dict]:
        """Send records from the front of `queue` until it is empty or the backend fails; return the rest.
        Artifacts that fail, or wait for their own retry, go to the side spool."""
        aside: list[dict] = []
        try:
            return self._process_into(queue, aside)
        finally:
            self._spool(aside, self.artifacts)

    def _process_into(self, queue: deque[dict], aside: list[dict]) -> list[dict]:
        while queue:
            batch, used = _merge_metrics(queue)
            try:
                # A checkpoint's deletion waits behind the uploads waiting aside, one of which may be that file.
                if batch["op"] in ARTIFACT_OPS and self._artifacts_held():
                    aside.append({**batch, "run": self._run_id(batch)})  # behind those already waiting
                    queue.popleft()
                    continue
                self._send(batch)
            except Exception as err:
                if batch["op"] in ARTIFACT_OPS and not refused(err):
                    self._artifact_failed(err)
                    aside.append({**batch, "run": self._run_id(batch)})
                    queue.popleft()
                    continue
                if not refused(err):
                    self.note_failure(err)
                    return list(queue)
                for _ in range(used):
                    queue.popleft()
                singles = _split(batch)
                if len(singles) > 1:  # retry entry by entry, dropping only the refused ones
                    queue.extendleft(reversed(singles))
                else:
                    log.warning("tracking: %s record dropped, refused by MLflow: %s", batch["op"], err)
                    _discard_owned(batch, self.owned_root)
                continue
            for _ in range(used):
                queue.popleft()
            _discard_owned(batch, self.owned_root)
            if batch["op"] == "artifact":
                self._artifact_timeouts, self._artifact_failing = 0, False
            if self._failures:
                self._failures, self._retry_at = 0, 0.0
                log.warning("tracking: %s answers again", redact(self.uri))
        return []

    # ---------------------------------------------------------------- the background thread

    def _run(self) -> None:
        """Drain the spool at the retry interval while it holds anything; sleep until something is spooled."""
        while not self._stopped.is_set():
            due = self._due()
            if due is None:
                self._wake.wait()
                self._wake.clear()
                continue
            delay = due - time.monotonic()
            if delay > 0:
                self._stopped.wait(delay)
                continue
            try:
                self.drain()
            except Exception as err:  # a bug or a full disk must not end the thread silently with records left
                log.error("tracking: background replay of %s failed: %s", self.spool.path, err)
                self.note_failure(err)

    # ---------------------------------------------------------------- requests

    def _resolved(self, record: dict) -> dict:
        """`record` with its placeholder run key replaced by the run id, once the run exists."""
        run = self.ids.get(record["run"])
        return record if run is None else {**record, "run": run}

    def _run_id(self, record: dict) -> str:
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
            client.log_batch(self._run_id(record), params=params, synchronous=True)
        elif op == "metrics":
            metrics = [Metric(k, v, ts, step) for k, v, ts, step in record["metrics"]]
            client.log_batch(self._run_id(record), metrics=metrics, synchronous=True)
        elif op == "tags":
            tags = [RunTag(k, v) for k, v in record["tags"].items()]
            client.log_batch(self._run_id(record), tags=tags, synchronous=True)
        elif op == "artifact":
            path = Path(record["path"])
            if not path.exists():
                raise Refused(f"artifact {path} no longer exists")
            upload = client.log_artifacts if path.is_dir() else client.log_artifact
            with artifact_timeout(self.artifact_timeout_s):
                upload(self._run_id(record), str(path), record.get("artifact_path"))
        elif op == "delete":  # not in MlflowClient: through the run's artifact repository (a no-op when gone)
            repo = get_artifact_repository(client.get_run(self._run_id(record)).info.artifact_uri, self.uri)
            repo.delete_artifacts(record["delete"])
        elif op == "complete":
            client.set_tag(self._run_id(record), COMPLETE_TAG, record["complete"])
        elif op == "end":
            client.set_terminated(self._run_id(record), status=record["status"], end_time=record["end_time"])
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


@contextmanager
def artifact_timeout(seconds: int) -> Iterator[None]:
    """MLflow's request timeouts set to `seconds` for an upload (one upload at a time in the process). A small
    request that another thread makes meanwhile gets that timeout too: a silent host costs it longer."""
    with _TIMEOUT_LOCK:
        saved = {key: os.environ.get(key) for key in _TIMEOUT_ENV}
        os.environ.update(dict.fromkeys(_TIMEOUT_ENV, str(int(seconds))))
        try:
            yield
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


def _timed_out(err: BaseException) -> bool:
    """Whether `err` (or an error it was raised from) is a timeout: the store took the connection and stalled."""
    seen: BaseException | None = err
    while seen is not None:
        if isinstance(seen, TimeoutError) or "Timeout" in type(seen).__name__ or "timed out" in str(seen):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


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


def _discard_owned(record: dict, owned_root: Path) -> None:
    """Delete a file the tracker wrote for upload (log_dict, log_figure) once it is done with: its folder, one
    of those the tracker makes directly under `owned_root`, and nothing else, whatever a spool line says."""
    if record["op"] != "artifact" or not record.get("owned"):
        return
    folder = Path(record["path"]).parent
    if folder.is_symlink() or folder.resolve().parent != owned_root.resolve():
        log.warning("tracking: not deleting %s: not a folder the tracker made under %s", folder, owned_root)
        return
    shutil.rmtree(folder, ignore_errors=True)
