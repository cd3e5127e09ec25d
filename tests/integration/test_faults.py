"""Faults end to end (DESIGN.md, reliability): a loss driven to NaN, a tracking server that goes away and
comes back, a driver killed with SIGKILL and resumed, and the chaos benchmark that does all of it to a Ray run."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import torch
from mlflow.tracking import MlflowClient

from orchestrator.bench.chaos import plan
from orchestrator.build import build_runtime
from orchestrator.components.rollout import RolloutActor
from orchestrator.tracking.base import NoOpLogger
from orchestrator.tracking.mlflow import MlflowLogger
from orchestrator.tracking.server import free_port, start_local_server
from orchestrator.trainer import Trainer
from orchestrator.world import load_character_and_library
from workers.learners import base as learner_base
from workers.learners.vae import VAELearner

ROOT = Path(__file__).resolve().parents[2]


def finite(state: dict) -> bool:
    return all(bool(torch.isfinite(v).all()) for v in state.values() if isinstance(v, torch.Tensor))


def wait_until(condition, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


# ---------------------------------------------------------------- NaN


@pytest.mark.slow
def test_a_loss_driven_to_nan_skips_updates_and_no_nonfinite_weight_reaches_a_worker(smoke, monkeypatch):
    cfg = smoke("runtime=local", "algo.loop.checkpoint_every=0", "algo.loop.balance_every=0")
    character, _ = load_character_and_library(cfg)
    received: list = []  # every weights object a rollout worker was given
    set_weights = RolloutActor.set_weights
    monkeypatch.setattr(RolloutActor, "set_weights", lambda self, w: (received.append(w), set_weights(self, w))[1])
    trainer = Trainer(cfg, build_runtime(cfg), NoOpLogger(), character)
    trainer.method.start(trainer)
    good = [trainer.step() for _ in range(3)]
    assert good[-1]["vae/version"] > 0 and good[-1]["vae/skipped_updates"] == 0

    # 1. The VAE's loss is NaN (as from a poisoned batch): every update is skipped, the version stands still.
    loss = VAELearner.loss
    monkeypatch.setattr(VAELearner, "loss", lambda self, b: (lambda t: (t[0] * float("nan"), t[1]))(loss(self, b)))
    nan = [trainer.step() for _ in range(3)]
    assert all(m["vae/skipped_updates"] > 0 for m in nan)
    assert nan[-1]["vae/skipped_updates"] > good[-1]["vae/skipped_updates"]
    assert {m["vae/version"] for m in nan} == {good[-1]["vae/version"]}
    assert all(m["loop/nonfinite_weights_skipped"] == 0 for m in nan)  # nothing non-finite was offered

    # 2. A learner without its own guard whose step left a NaN in the weights: the trainer refuses them.
    monkeypatch.setattr(VAELearner, "loss", loss)
    monkeypatch.setattr(learner_base, "all_finite", lambda tensors: True)
    poisoned = VAELearner.after_update

    def after_update(self):
        poisoned(self)
        next(iter(self.module.parameters())).data[0] = float("nan")

    monkeypatch.setattr(VAELearner, "after_update", after_update)
    bad = [trainer.step() for _ in range(3)]
    vae = trainer.handles["vae"].learner
    assert not finite(vae.get_weights().state)  # offered to the trainer ...
    assert bad[-1]["loop/nonfinite_weights_skipped"] >= 1  # ... and refused
    assert {m["rollout/policy_version"] for m in bad} == {good[-1]["rollout/policy_version"]}
    assert trainer.step()["throughput/samples_per_s"] > 0  # the workers collect on with the last good weights

    assert received and all(finite(w.state) for w in received)
    assert max(w.version for w in received) == good[-1]["rollout/policy_version"]
    for worker in trainer.workers:
        assert finite(worker.worker.policy.controller.state_dict())


# ---------------------------------------------------------------- the tracking server goes away


@pytest.mark.slow
def test_metrics_logged_while_the_server_was_down_reach_it_without_further_logging(tmp_path):
    port = free_port()
    store, artifacts = f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "artifacts"
    server = start_local_server(store, artifacts, port=port)
    try:
        tracker = MlflowLogger(server.uri, "faults", run_dir=tmp_path / "run", retry_interval_s=0.5)
        for step in range(3):
            tracker.log_metrics({"loss": float(step)}, step=step)
        assert tracker.pending() == 0
        server.stop()
        for step in range(3, 10):
            tracker.log_metrics({"loss": float(step)}, step=step)  # spooled
        assert tracker.pending() == 7
        server = start_local_server(store, artifacts, port=port)  # back on the same port and store
        # Nothing more is logged: the background thread alone sends the spool.
        assert wait_until(lambda: tracker.pending() == 0, timeout_s=120)
        client = MlflowClient(server.uri)
        history = sorted((m.step, m.value) for m in client.get_metric_history(tracker.run_id, "loss"))
        assert history == [(s, float(s)) for s in range(10)]
        tracker.close()
        assert client.get_run(tracker.run_id).info.status == "FINISHED"
    finally:
        server.stop()


# ---------------------------------------------------------------- a killed driver


def ray_processes_of(pid: int, known: list[psutil.Process] = ()) -> list[psutil.Process]:
    """The processes of the Ray that the driver `pid` started: its descendants (while it lives), those of
    `known` ones, and any whose command line names its session directory (`.../session_<date>_<pid>`)."""
    found: dict[int, psutil.Process] = {p.pid: p for p in known if p.is_running()}  # is_running: not a reused pid
    for root in [pid, *found]:
        try:
            process = found.get(root) or psutil.Process(root)
            found.update({c.pid: c for c in process.children(recursive=True)})
        except psutil.NoSuchProcess:
            pass
    session = re.compile(rf"session_[0-9_-]+_{pid}(?![0-9])")
    for p in psutil.process_iter(["cmdline"]):
        if any(session.search(arg) for arg in p.info["cmdline"] or ()):
            found.setdefault(p.pid, p)
    return list(found.values())


def terminate(processes: list[psutil.Process]) -> None:
    """End these processes (and only these): SIGTERM, then SIGKILL for those still there after 10 s."""
    for p in processes:
        try:
            p.terminate()
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(processes, timeout=10)
    for p in alive:
        try:
            p.kill()
        except psutil.NoSuchProcess:
            pass
    psutil.wait_procs(alive, timeout=10)


def orchestrator(*args: str, log: Path | None = None) -> subprocess.Popen:
    """`python -m orchestrator` with `args`; its output to `log` (read after it ends) or to pipes."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    out = subprocess.PIPE if log is None else log.open("w")
    return subprocess.Popen(
        [sys.executable, "-m", "orchestrator", *args],
        cwd=ROOT,
        env=env,
        stdout=out,
        stderr=subprocess.STDOUT if log is not None else subprocess.PIPE,
        text=True,
    )


@pytest.mark.ray
@pytest.mark.slow
def test_a_ray_driver_killed_with_sigkill_resumes_into_the_same_mlflow_run(tmp_path):
    run_dir, every = tmp_path / "run", 3
    common = ["runtime=ray", "scale=smoke", "motion=walk", "progress=false", f"run_dir={run_dir}"]
    common += [f"algo.loop.checkpoint_every={every}", "eval.at_start=false", "tracking.log_model=false"]
    log = tmp_path / "killed.log"
    proc = orchestrator(*common, "algo.loop.iterations=1000", log=log)
    ckpt_dir = run_dir / "checkpoints"
    ray_processes: list[psutil.Process] = []
    try:
        assert wait_until(lambda: proc.poll() is not None or any(ckpt_dir.glob("ckpt-*.pt")), 300)
        assert proc.poll() is None, log.read_text()[-3000:]
        time.sleep(1.0)  # a little past the checkpoint: the kill loses the iterations since
        ray_processes = ray_processes_of(proc.pid)  # the driver's Ray, found before the kill orphans it
        assert ray_processes
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        # Only the killed driver's own Ray processes (never `ray stop`: other Rays may run on this machine).
        terminate(ray_processes_of(proc.pid, ray_processes))
    killed_at = max(int(p.stem.split("-")[1]) for p in ckpt_dir.glob("ckpt-*.pt"))
    run_id = json.loads((run_dir / "run.json").read_text())["run_id"]
    client = MlflowClient(f"sqlite:///{run_dir}/mlflow.db")
    logged = [m.step for m in client.get_metric_history(run_id, "throughput/iteration_s")]
    per_iteration = 2 * 8 * 16  # workers x envs x collect steps at smoke scale
    last_logged = max(logged) // per_iteration
    assert killed_at >= last_logged - every  # at most one checkpoint interval is lost

    # Past every iteration the killed driver logged (it may have logged up to `every` - 1 past its checkpoint), so
    # that the last two steps can only be the resumed run's.
    target = max(killed_at, last_logged) + 2
    resumed = orchestrator(*common, f"algo.loop.iterations={target}", "resume=true")
    try:
        out, err = resumed.communicate(timeout=400)
    finally:
        if resumed.poll() is None:
            resumed.kill()
    assert resumed.returncode == 0, err[-3000:]
    assert f"at iteration {killed_at}" in err
    assert json.loads((run_dir / "run.json").read_text())["run_id"] == run_id
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED"
    assert len(client.search_runs([run.info.experiment_id])) == 1
    steps = sorted({m.step for m in client.get_metric_history(run_id, "throughput/iteration_s")})
    assert steps[-2:] == [per_iteration * i for i in (target - 1, target)]  # continued from the checkpoint


# ---------------------------------------------------------------- the chaos benchmark


def test_the_chaos_plan_spreads_the_faults_over_the_run():
    # 90 s: the outage from 15 % (13.5 s) for 30 s; the learners and the replay at 30, 50, 70 % (27, 45, 63 s);
    # a rollout worker every 20 s before 85 % (76.5 s), the two in turn.
    faults = plan(1.5, kill_every=20, outage=30, workers=2)
    assert [(round(f.at_s, 6), f.target) for f in faults] == [
        (13.5, "tracking server"),
        (20, "rollout-0"),
        (27, "learner-world_model"),
        (40, "rollout-1"),
        (45, "learner-vae"),
        (60, "rollout-0"),
        (63, "replay"),
    ]
    assert faults[0].down_s == 30
    assert plan(1.0, kill_every=60, outage=600, workers=2)[0].down_s == pytest.approx(33)  # clipped: ends by 70 %


@pytest.mark.ray
@pytest.mark.slow
def test_the_chaos_benchmark_recovers_every_fault_and_loses_no_metric(tmp_path):
    out = tmp_path / "chaos.json"
    args = ["--minutes", "1.5", "--kill-every", "20", "--outage", "30", "--out", str(out), "--json"]
    args += ["--run-dir", str(tmp_path / "chaos")]
    proc = subprocess.run(
        [sys.executable, "-m", "orchestrator.bench", "chaos", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    targets = {f["target"] for f in result["faults"] if f["injected"]}
    assert {"tracking server", "learner-world_model", "learner-vae", "replay"} <= targets
    assert any(t.startswith("rollout-") for t in targets)
    assert result["error"] is None
    assert result["injected"] == result["planned"] == result["recovered"], result["faults"]
    assert result["recoveries"] >= 3  # each learner and the replay buffer reloaded from a checkpoint
    assert result["iterations"] > 0 and result["status"] == "FINISHED"
    assert result["metrics_logged"] == result["iterations"]
    assert result["metrics_lost"] == 0 and result["spool_left"] == 0
    assert np.isfinite(result["final"]["throughput/iteration_s"])
