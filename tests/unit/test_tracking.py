"""Trackers: config flattening, the no-op twin, and the MLflow tracker on an embedded SQLite store,
including its disk spool for an unreachable server (replayed here into a store without a server;
the round trip through a real server is in tests/integration/test_tracking_server.py)."""

from __future__ import annotations

import hashlib
import json
import logging
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from orchestrator.tracking import NoOpLogger, flatten
from orchestrator.tracking.base import MAX_PARAM_VALUE_LENGTH, TRUNCATION_MARK, truncate
from orchestrator.tracking.mlflow import SPOOL_FILE, MlflowLogger, replay_spool
from orchestrator.tracking.server import free_port
from orchestrator.tracking.uri import embedded_uri


def history(client: MlflowClient, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted((m.step, m.value) for m in client.get_metric_history(run_id, key))


def artifacts(client: MlflowClient, run_id: str, path: str | None = None) -> set[str]:
    return {a.path for a in client.list_artifacts(run_id, path)}


class FakeFigure:
    """Stands in for a matplotlib figure: all a tracker needs is savefig(path)."""

    def savefig(self, path) -> None:
        Path(path).write_bytes(b"\x89PNG fake")


# ---------------------------------------------------------------- flatten and the no-op tracker


def test_flatten_known_answer():
    config = {
        "algo": {"alpha": 3e-4, "prior": {"type": "learned", "clamp": [-5, 2]}},
        "motion": {"clips": ["walk", "run"], "weights": {}},
        "stages": [{"name": "tracker"}, {"name": "physicsvae"}],
        "seed": 0,
        "resume": False,
        "uri": None,
    }
    assert flatten(config) == {
        "algo.alpha": "0.0003",
        "algo.prior.type": "learned",
        "algo.prior.clamp": "[-5, 2]",  # a list of scalars stays one value
        "motion.clips": "['walk', 'run']",
        "motion.weights": "{}",
        "stages.0.name": "tracker",  # a list of mappings nests by index
        "stages.1.name": "physicsvae",
        "seed": "0",
        "resume": "False",
        "uri": "None",
    }
    assert flatten({"a": {"b": 1}}, prefix="cfg") == {"cfg.a.b": "1"}


def test_flatten_truncates_long_values_to_the_limit():
    out = flatten({"clips": "x" * 10_000, "short": "y" * MAX_PARAM_VALUE_LENGTH})
    assert len(out["clips"]) == MAX_PARAM_VALUE_LENGTH
    assert out["clips"].endswith(TRUNCATION_MARK)
    assert out["short"] == "y" * MAX_PARAM_VALUE_LENGTH  # exactly at the limit: untouched
    assert truncate("abcdefghijklmnopq", limit=len(TRUNCATION_MARK) + 2) == "ab" + TRUNCATION_MARK


def test_noop_tracker_accepts_everything(tmp_path):
    class Figure:
        def savefig(self, path):
            raise AssertionError("a no-op tracker draws nothing")

    with NoOpLogger() as tracker:
        tracker.log_params({"a": 1})
        tracker.log_metrics({"vae/loss": 1.0}, step=0)
        tracker.set_tags({"stage": "x"})
        tracker.log_artifact(tmp_path / "missing.pt", "checkpoints")
        tracker.log_dict({"a": 1}, "config.json")
        tracker.log_figure(Figure(), "plots/f.png")
        tracker.flush()
        assert tracker.run_id is None
    tracker.close("FAILED")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- the embedded store


@pytest.fixture
def run_dir(tmp_path) -> Path:
    return tmp_path / "run"


def test_embedded_run_gets_params_metrics_tags_and_artifacts(run_dir, tmp_path):
    tracker = MlflowLogger(None, "default", run_name="alpha=3e-4 seed=1", tags={"algo": "physicsvae"}, run_dir=run_dir)
    calls = []
    log_batch = tracker._sender.client.log_batch
    tracker._sender.client.log_batch = lambda *a, **k: (calls.append(k), log_batch(*a, **k))[1]

    tracker.log_params({f"p{i:03d}": i for i in range(250)})  # MLflow takes 100 params per request
    for step in (0, 1000, 2000):
        tracker.log_metrics({"vae/loss": step / 1000, "rollout/return": 2.0, "throughput/sps": 3.0}, step=step)
    tracker.set_tags({"stage": "physicsvae"})
    (tmp_path / "ckpt.pt").write_bytes(b"weights")
    tracker.log_artifact(tmp_path / "ckpt.pt", "checkpoints")
    tracker.log_dict({"algo": {"alpha": 3e-4}}, "config.json")
    tracker.log_dict({"a": [1, 2]}, "eval/report.yaml")
    tracker.log_figure(FakeFigure(), "eval/fall.png")
    tracker.close()

    assert [len(c.get("params", ())) for c in calls[:3]] == [100, 100, 50]
    assert [len(c["metrics"]) for c in calls if c.get("metrics")] == [3, 3, 3]  # one request per call, not per metric
    client = MlflowClient(embedded_uri(run_dir))
    run = client.get_run(tracker.run_id)
    assert run.info.status == "FINISHED"
    assert run.info.run_name == "alpha=3e-4 seed=1"
    assert run.data.params["p249"] == "249" and len(run.data.params) == 250
    assert run.data.tags["algo"] == "physicsvae" and run.data.tags["stage"] == "physicsvae"
    assert history(client, tracker.run_id, "vae/loss") == [(0, 0.0), (1000, 1.0), (2000, 2.0)]
    assert run.info.artifact_uri.startswith((run_dir / "mlartifacts").resolve().as_uri())
    assert artifacts(client, tracker.run_id) == {"artifacts.sha256.json", "checkpoints", "config.json", "eval"}
    assert artifacts(client, tracker.run_id, "eval") == {"eval/report.yaml", "eval/fall.png"}
    assert artifacts(client, tracker.run_id, "checkpoints") == {"checkpoints/ckpt.pt"}
    # The manifest, last: every file by its SHA-256, and the manifest's own digest as the completion tag.
    text = Path(client.download_artifacts(tracker.run_id, "artifacts.sha256.json", str(tmp_path))).read_text()
    manifest = json.loads(text)
    assert set(manifest) == {"checkpoints/ckpt.pt", "config.json", "eval/report.yaml", "eval/fall.png"}
    assert manifest["checkpoints/ckpt.pt"] == hashlib.sha256(b"weights").hexdigest()
    assert run.data.tags["artifacts_sha256"] == hashlib.sha256(text.encode()).hexdigest()
    local = Path(client.download_artifacts(tracker.run_id, "eval/report.yaml", str(tmp_path)))
    assert local.read_text() == "a:\n- 1\n- 2\n"
    config = Path(client.download_artifacts(tracker.run_id, "config.json", str(tmp_path)))
    assert json.loads(config.read_text()) == {"algo": {"alpha": 3e-4}}
    assert tracker.pending() == 0 and not (run_dir / SPOOL_FILE).exists()
    assert not any((run_dir / "tracking-artifacts").iterdir())  # log_dict's files are gone once uploaded


def test_metrics_are_buffered_for_flush_every_calls(run_dir):
    tracker = MlflowLogger(None, "default", run_dir=run_dir, flush_every=3)
    client = MlflowClient(embedded_uri(run_dir))
    tracker.log_metrics({"a": 1.0}, step=1)
    tracker.log_metrics({"a": 2.0}, step=2)
    assert history(client, tracker.run_id, "a") == []
    tracker.log_metrics({"a": 3.0}, step=3)
    assert history(client, tracker.run_id, "a") == [(1, 1.0), (2, 2.0), (3, 3.0)]
    tracker.log_metrics({"a": 4.0}, step=4)
    tracker.close()  # close sends what is buffered
    assert history(client, tracker.run_id, "a")[-1] == (4, 4.0)


def test_resume_continues_the_same_run(run_dir, caplog):
    first = MlflowLogger(None, "default", run_name="r", run_dir=run_dir)
    first.log_params({"algo.alpha": "0.0003", "seed": 1})
    first.log_metrics({"vae/loss": 1.0}, step=100)
    first.close("KILLED")

    second = MlflowLogger(None, "default", run_id=first.run_id, tags={"resumed": "yes"}, run_dir=run_dir)
    assert second.run_id == first.run_id
    client = MlflowClient(embedded_uri(run_dir))
    assert client.get_run(first.run_id).info.status == "RUNNING"
    with caplog.at_level(logging.WARNING):
        second.log_params({"algo.alpha": "0.0003", "seed": 2, "new": "x"})  # same, changed, new
    assert "cannot change it" in caplog.text
    second.log_metrics({"vae/loss": 0.5}, step=200)
    second.close()

    run = client.get_run(first.run_id)
    assert run.info.status == "FINISHED"
    assert run.data.params == {"algo.alpha": "0.0003", "seed": "1", "new": "x"}
    assert run.data.tags["resumed"] == "yes"
    assert history(client, first.run_id, "vae/loss") == [(100, 1.0), (200, 0.5)]
    assert len(client.search_runs([run.info.experiment_id])) == 1


def test_child_run_names_its_parent(run_dir):
    parent = MlflowLogger(None, "ablation_alpha", run_name="sweep", tags={"sweep_id": "s1"}, run_dir=run_dir)
    child = MlflowLogger(None, "ablation_alpha", run_name="alpha=1e-3", parent_run_id=parent.run_id, run_dir=run_dir)
    child.log_metrics({"eval/time_until_fall": 12.0}, step=10)
    child.close()
    parent.close()
    client = MlflowClient(embedded_uri(run_dir))
    assert client.get_run(child.run_id).data.tags["mlflow.parentRunId"] == parent.run_id
    assert child.run_id != parent.run_id


def test_refused_entries_are_dropped_and_the_rest_of_the_batch_kept(run_dir, caplog):
    tracker = MlflowLogger(None, "default", run_dir=run_dir)
    with caplog.at_level(logging.WARNING):
        tracker.log_params({"good": 1, "bad key!*": 2, "also_good": 3})
        tracker.log_metrics({"ok": 1.0, "no good?": 2.0}, step=0)
    tracker.close()
    assert "refused by MLflow" in caplog.text
    run = MlflowClient(embedded_uri(run_dir)).get_run(tracker.run_id)
    assert run.data.params == {"good": "1", "also_good": "3"}
    assert run.data.metrics == {"ok": 1.0}
    assert tracker.pending() == 0  # refusals are not spooled: they would fail on every replay


# ---------------------------------------------------------------- the spool


def test_unreachable_server_spools_and_the_spool_replays(run_dir, tmp_path):
    uri = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    start = time.perf_counter()
    tracker = MlflowLogger(uri, "default", run_name="offline", tags={"stage": "vae"}, run_dir=run_dir)
    assert tracker.run_id is None  # the run creation itself is spooled
    tracker.log_params({"seed": 0})
    for step in range(20):
        tracker.log_metrics({"vae/loss": float(step), "rollout/return": 1.0}, step=step)
    (tmp_path / "ckpt.pt").write_bytes(b"weights")
    tracker.log_artifact(tmp_path / "ckpt.pt", "checkpoints")
    tracker.log_dict({"a": 1}, "config.json")
    tracker.flush()  # tries again, still refused
    tracker.close()
    elapsed = time.perf_counter() - start
    assert elapsed < 10, f"an unreachable server cost {elapsed:.1f} s"  # MLflow's defaults retry for minutes
    assert tracker.pending() == 1 + 1 + 20 + 2 + 2 + 1  # create, params, metrics, artifacts, manifest+tag, end
    lines = (run_dir / SPOOL_FILE).read_text().splitlines()
    assert [json.loads(line)["op"] for line in lines[:3]] == ["create", "params", "metrics"]

    # The same records replayed into a store that answers (the run's embedded one): the run is created then.
    assert replay_spool(run_dir, None) == 0
    assert not (run_dir / SPOOL_FILE).exists()
    client = MlflowClient(embedded_uri(run_dir))
    (run,) = client.search_runs([client.get_experiment_by_name("default").experiment_id])
    assert run.info.run_name == "offline" and run.info.status == "FINISHED"
    assert run.data.tags["stage"] == "vae" and run.data.params == {"seed": "0"}
    assert history(client, run.info.run_id, "vae/loss") == [(s, float(s)) for s in range(20)]
    assert artifacts(client, run.info.run_id) == {"artifacts.sha256.json", "checkpoints", "config.json"}
    assert run.data.tags["artifacts_sha256"]  # complete once replayed: set after the uploads


def test_a_new_tracker_on_the_run_dir_replays_what_an_earlier_one_left(run_dir):
    offline = MlflowLogger(f"http://127.0.0.1:{free_port()}", "default", run_name="first", run_dir=run_dir)
    offline.log_metrics({"a": 1.0}, step=1)
    offline.close()
    assert offline.pending() == 5  # create, metrics, the manifest and its tag, end

    online = MlflowLogger(None, "default", run_name="second", run_dir=run_dir)  # replays before creating its run
    assert online.pending() == 0
    client = MlflowClient(embedded_uri(run_dir))
    runs = client.search_runs([client.get_experiment_by_name("default").experiment_id])
    (first,) = [r for r in runs if r.info.run_name == "first"]
    assert history(client, first.info.run_id, "a") == [(1, 1.0)]
    online.close()


def test_a_run_that_cannot_be_resumed_starts_anew(run_dir, caplog):
    with caplog.at_level(logging.WARNING):
        tracker = MlflowLogger(None, "default", run_id="0" * 32, run_dir=run_dir)
    assert "cannot be resumed" in caplog.text
    assert tracker.run_id is not None and tracker.run_id != "0" * 32
    tracker.close()


def test_a_damaged_spool_line_is_skipped(run_dir, caplog):
    offline = MlflowLogger(f"http://127.0.0.1:{free_port()}", "default", run_name="cut", run_dir=run_dir)
    offline.log_metrics({"a": 1.0}, step=1)
    with (run_dir / SPOOL_FILE).open("a") as f:
        f.write('{"op": "metrics", "run": "pend')  # a write cut short by a crash
    with caplog.at_level(logging.WARNING):
        online = MlflowLogger(None, "default", run_name="next", run_dir=run_dir)
    assert "is not a record; skipped" in caplog.text
    assert online.pending() == 0 and not (run_dir / SPOOL_FILE).exists()
    client = MlflowClient(embedded_uri(run_dir))
    runs = client.search_runs([client.get_experiment_by_name("default").experiment_id])
    assert {r.info.run_name for r in runs} == {"cut", "next"}
    online.close()


def test_the_interface_loads_no_mlflow():
    code = "import orchestrator.tracking, sys; print('mlflow' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_a_backend_that_fails_then_recovers(run_dir):
    tracker = MlflowLogger(None, "default", run_dir=run_dir, retry_interval_s=60)
    client = tracker._sender.client
    log_batch = client.log_batch

    def down(*args, **kwargs):
        raise ConnectionError("connection refused")

    client.log_batch = down
    tracker.log_metrics({"a": 1.0}, step=1)
    tracker.log_metrics({"a": 2.0}, step=2)  # within the retry interval: spooled without a try
    assert tracker.pending() == 2
    client.log_batch = log_batch
    tracker.log_metrics({"a": 3.0}, step=3)  # still within the interval
    assert tracker.pending() == 3
    tracker.flush()  # tries regardless of the interval; success ends the outage
    assert tracker.pending() == 0
    tracker.log_metrics({"a": 4.0}, step=4)
    assert tracker.pending() == 0  # sent directly
    tracker.close()
    assert history(MlflowClient(embedded_uri(run_dir)), tracker.run_id, "a") == [(s, float(s)) for s in (1, 2, 3, 4)]


# ---------------------------------------------------------------- the background replay


def wait_until(condition, timeout_s: float = 30.0) -> bool:
    """Poll `condition` until it holds or `timeout_s` passes; whether it held."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_the_spool_drains_in_the_background_while_nothing_more_is_logged(run_dir):
    tracker = MlflowLogger(None, "default", run_dir=run_dir, retry_interval_s=0.05)
    client = tracker._sender.client
    log_batch = client.log_batch

    def down(*args, **kwargs):
        raise ConnectionError("connection refused")

    client.log_batch = down
    for step in range(5):
        tracker.log_metrics({"a": float(step)}, step=step)
    assert tracker.pending() == 5
    client.log_batch = log_batch  # the backend is back; the run logs nothing more
    assert wait_until(lambda: tracker.pending() == 0)
    assert history(MlflowClient(embedded_uri(run_dir)), tracker.run_id, "a") == [(s, float(s)) for s in range(5)]
    thread = tracker._sender._thread
    assert thread is not None and thread.daemon and thread.is_alive()  # idle, waiting for the next outage
    tracker.close()
    assert not thread.is_alive()
    assert MlflowClient(embedded_uri(run_dir)).get_run(tracker.run_id).info.status == "FINISHED"


def test_records_logged_during_a_background_replay_are_kept_in_order(run_dir):
    """The training thread appends while the background thread sends the spool: it does not wait for the
    request, nothing it appends is lost when the replay rewrites the spool, and nothing is sent twice."""
    tracker = MlflowLogger(None, "default", run_dir=run_dir, retry_interval_s=0.05)
    client = tracker._sender.client
    log_batch = client.log_batch
    started, release = threading.Event(), threading.Event()

    def down(*args, **kwargs):
        raise ConnectionError("connection refused")

    def slow(*args, **kwargs):
        started.set()
        assert release.wait(30)
        return log_batch(*args, **kwargs)

    client.log_batch = down
    for step in range(10):
        tracker.log_metrics({"a": float(step)}, step=step)
    client.log_batch = slow
    assert started.wait(30)  # the background thread is inside a request with the first 10
    for step in range(10, 20):
        tracker.log_metrics({"a": float(step)}, step=step)  # would hang here if it waited for the request
    assert tracker.pending() == 20  # all appended behind the records in flight
    release.set()
    assert wait_until(lambda: tracker.pending() == 0)
    tracker.close()
    steps = [m.step for m in MlflowClient(embedded_uri(run_dir)).get_metric_history(tracker.run_id, "a")]
    assert sorted(steps) == list(range(20))  # each once
    assert not (run_dir / SPOOL_FILE).exists()


def test_close_stops_a_background_thread_that_is_still_retrying(run_dir):
    uri = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    tracker = MlflowLogger(uri, "default", run_dir=run_dir, retry_interval_s=0.05)
    tracker.log_metrics({"a": 1.0}, step=1)
    thread = tracker._sender._thread
    assert thread is not None and thread.is_alive()
    tracker.close()
    assert not thread.is_alive()
    assert tracker.pending() == 5  # create, metrics, manifest, tag, end: left for the next tracker or replay_spool


def test_a_spool_of_only_damaged_lines_is_cleared_not_retried_forever(run_dir):
    run_dir.mkdir(parents=True)
    (run_dir / SPOOL_FILE).write_text('{"op": "metrics", "ru\n')  # nothing in it can be sent
    tracker = MlflowLogger(None, "default", run_dir=run_dir, retry_interval_s=0.05)
    assert tracker.pending() == 0 and not (run_dir / SPOOL_FILE).exists()
    tracker.log_metrics({"a": 1.0}, step=1)
    tracker.close()
    assert history(MlflowClient(embedded_uri(run_dir)), tracker.run_id, "a") == [(1, 1.0)]
