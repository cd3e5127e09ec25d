"""Chaos: a real ControlVAE run on Ray, tracked by a local MLflow server, while faults are injected into it.

The run is the service's own (`orchestrator.build.run`): Ray actors, checkpoints every few iterations,
`algo.loop.max_minutes` of training, at the smoke scale unless overridden. From threads, once the first
checkpoint is written and over the time the run has left then:

- a rollout worker is killed every `kill_every` seconds (the workers in turn);
- each learner and the replay buffer are killed once, spread over the run;
- the tracking server is stopped for `outage` seconds, then started again on the same port and store.

A kill is `ray.kill(actor, no_restart=False)`, as a crash: it is recovered when Ray's state API shows the
actor alive again with one more restart and, for a learner or the replay buffer, when the trainer reloaded
it from the last checkpoint (its log line, and `loop/recoveries` counts them). The outage is recovered when the
tracker's spool empties in the background while the run is still training (not at its `close`).
At the end the server's history of `throughput/iteration_s`, logged once per iteration, is set against the
iterations the run did (its last checkpoint): every iteration logged was received, so none may be lost.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import platform
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from orchestrator.tracking.mlflow import SPOOL_FILE

ITERATION_METRIC = "throughput/iteration_s"  # logged once per iteration
STATEFUL = ("learner-world_model", "learner-vae", "replay")  # reloaded from a checkpoint when they come back


@dataclass
class Fault:
    at_s: float  # seconds after the run's first checkpoint
    kind: str  # kill | outage
    target: str  # actor name, or the tracking server
    down_s: float = 0.0  # outage: how long the server stays down
    injected: bool = False
    recovered: bool = False
    seconds: float | None = None  # to the restart (kill), or from the server's return to an empty spool (outage)
    detail: str = ""


def default_outage(minutes: float) -> float:
    """A third of the run, three minutes at most."""
    return min(180.0, 20.0 * minutes)


def plan(minutes: float, kill_every: float, outage: float, workers: int) -> list[Fault]:
    """The faults in time order: the outage from 15 % of the run (ending by 70 % of it, so that the spool
    drains while the run trains), the learners and the replay buffer at 30, 50 and 70 %, rollout workers
    in turn every `kill_every` seconds until 85 %."""
    duration = 60.0 * minutes
    faults = [Fault(0.15 * duration, "outage", "tracking server", down_s=min(outage, 0.55 * duration))]
    faults += [Fault(f * duration, "kill", name) for f, name in zip((0.3, 0.5, 0.7), STATEFUL, strict=True)]
    k = 1
    while k * kill_every < 0.85 * duration:
        faults.append(Fault(k * kill_every, "kill", f"rollout-{(k - 1) % workers}"))
        k += 1
    return sorted(faults, key=lambda f: f.at_s)


class Reloads(logging.Handler):
    """The trainer's word that it reloaded a component Ray had restarted (`Trainer.check_alive` logs it)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.keys: list[str] = []  # world_model, vae, replay, once per reload

    def emit(self, record: logging.LogRecord) -> None:
        if "restarted" in str(record.msg) and record.args:
            self.keys.append(str(record.args[0]))


class Injector(threading.Thread):
    """Injects the planned faults into the Ray run of this process and the tracking server, each from its own
    thread at its time, and checks that each recovers. The plan starts at the run's first checkpoint, over
    what is left of `minutes` then, so that every kill of a stateful component has a checkpoint to go back to.
    """

    def __init__(
        self,
        minutes: float,
        kill_every: float,
        outage: float,
        server: Any,
        store: tuple[str, Path],
        train_dir: Path,
        say: Callable[[str], None],
    ):
        super().__init__(name="chaos", daemon=True)
        self.minutes, self.kill_every, self.outage = minutes, kill_every, outage
        self.faults: list[Fault] = []
        self.server = server  # replaced when restarted
        self.store = store  # the server's backend URI and artifact directory, to start it again
        self.train_dir = train_dir
        self.say = say
        self.done = threading.Event()  # the run is over: stop injecting and waiting
        self.restarts: dict[str, int] = {}  # Ray's restart count of each actor killed, last seen
        self.threads: list[threading.Thread] = []
        self.error: str | None = None

    def run(self) -> None:
        try:
            found = self._wait_for_start()
            if found is None:
                return
            namespace, workers, waited = found
            window = max(self.minutes - waited / 60.0, 0.0)
            self.say(f"chaos: first checkpoint {waited:.0f} s into the run; faults over the {60 * window:.0f} s left")
            self.faults = plan(window, self.kill_every, self.outage, workers)
            start = time.monotonic()
            for fault in self.faults:
                if self.done.wait(max(0.0, start + fault.at_s - time.monotonic())):
                    break
                target = self._outage if fault.kind == "outage" else self._kill
                thread = threading.Thread(target=self._guarded, args=(target, fault, namespace), daemon=True)
                thread.start()
                self.threads.append(thread)
        except Exception as err:  # reported, and every fault not verified counts as not recovered
            self.error = f"{type(err).__name__}: {err}"
            self.say(f"chaos: {self.error}")

    def join_all(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        for thread in [self, *self.threads]:
            thread.join(max(0.0, deadline - time.monotonic()))

    def _guarded(self, target: Callable[[Fault, str], None], fault: Fault, namespace: str) -> None:
        try:
            target(fault, namespace)
        except Exception as err:
            self.error = f"{type(err).__name__}: {err}"
            fault.detail = f"{fault.detail}; failed: {self.error}".lstrip("; ")
            self.say(f"chaos: {fault.target}: {self.error}")

    def _wait_for_start(self) -> tuple[str, int, float] | None:
        """(Ray namespace, rollout workers, seconds from the actors' creation to the first checkpoint) once the
        run's first checkpoint is written. The training budget starts a little after the actors' creation."""
        import ray

        namespace, workers, created = None, 0, 0.0
        while not self.done.wait(0.2):
            if namespace is None:
                if not ray.is_initialized():
                    continue
                try:  # the trainer spawns the stateful components first, then the workers
                    ray.get_actor("rollout-0", namespace=ray.get_runtime_context().namespace)
                except ValueError:
                    continue
                namespace, created = ray.get_runtime_context().namespace, time.monotonic()
            if any((self.train_dir / "checkpoints").glob("ckpt-*.pt")):
                while True:
                    try:
                        ray.get_actor(f"rollout-{workers}", namespace=namespace)
                    except ValueError:
                        break
                    workers += 1
                return namespace, workers, time.monotonic() - created
        return None

    def _kill(self, fault: Fault, namespace: str) -> None:
        import ray
        from ray.util.state import get_actor

        handle = ray.get_actor(fault.target, namespace=namespace)
        actor_id = handle._actor_id.hex()
        # This run's own cluster: without an address the state API refuses when other Rays run on the machine.
        address = ray.get_runtime_context().gcs_address
        before = get_actor(actor_id, address=address).num_restarts
        self.say(f"chaos: {fault.at_s:5.1f} s: killing {fault.target} (restarts so far {before})")
        t0 = time.monotonic()
        ray.kill(handle, no_restart=False)
        fault.injected = True
        while not self.done.wait(0.2) and time.monotonic() - t0 < 120:
            state = get_actor(actor_id, address=address)
            if state is not None and state.state == "ALIVE" and state.num_restarts > before:
                fault.recovered, fault.seconds = True, time.monotonic() - t0
                self.restarts[fault.target] = state.num_restarts
                fault.detail = f"Ray restart {state.num_restarts} after {fault.seconds:.1f} s"
                return
        fault.detail = "not seen alive again"

    def _outage(self, fault: Fault, namespace: str) -> None:
        from orchestrator.tracking.server import start_local_server

        seconds, old = fault.down_s, self.server
        self.say(f"chaos: {fault.at_s:5.1f} s: stopping the tracking server on port {old.port} for {seconds:.0f} s")
        old.stop()
        fault.injected = True
        self.done.wait(seconds)  # the server comes back even when the run ended meanwhile
        self.server = start_local_server(*self.store, port=old.port, log_path=old.log_path)
        back = time.monotonic()
        self.say(f"chaos: tracking server back on port {old.port}")
        while not self.done.wait(0.2):
            if not (self.train_dir / SPOOL_FILE).exists():
                fault.recovered, fault.seconds = True, time.monotonic() - back
                fault.detail = f"down {seconds:.0f} s; spool drained in the background {fault.seconds:.1f} s after"
                return
        fault.detail = f"down {seconds:.0f} s; the spool was not empty when the run ended"


def run(
    minutes: float,
    kill_every: float,
    outage: float | None,
    run_dir: Path,
    overrides: Sequence[str] = (),
    say: Callable[[str], None] = lambda m: print(m, file=sys.stderr, flush=True),
) -> dict[str, Any]:
    from orchestrator import build, checkpoint
    from orchestrator.compose import compose, validate
    from orchestrator.tracking.query import metric_steps, run_status_and_tags
    from orchestrator.tracking.server import start_local_server
    from orchestrator.tracking.uri import embedded_uri

    outage = default_outage(minutes) if outage is None else outage
    run_dir = Path(run_dir).resolve()
    train_dir = run_dir / "run"
    backend, artifacts = embedded_uri(run_dir / "server"), run_dir / "server" / "mlartifacts"
    artifacts.mkdir(parents=True, exist_ok=True)
    server = start_local_server(backend, artifacts, log_path=run_dir / "server" / "mlflow-server.log")
    config = [
        "runtime=ray", "scale=smoke", "motion=walk", "progress=false", "eval.at_start=false",
        "algo.loop.iterations=100000000", f"algo.loop.max_minutes={minutes}", "algo.loop.checkpoint_every=5",
        "runtime.max_restarts=1000", "tracking.experiment=chaos", *overrides,
    ]  # fmt: skip
    try:
        cfg = validate(compose([*config, f"run_dir={train_dir}", f"tracking.uri={server.uri}"]))
    except BaseException:
        server.stop()
        raise
    injector = Injector(minutes, kill_every, outage, server, (backend, artifacts), train_dir, say)
    reloads = Reloads()
    logging.getLogger("orchestrator.trainer").addHandler(reloads)
    injector.start()
    summary: dict[str, float] = {}
    error = None
    t0 = time.monotonic()
    try:
        with contextlib.redirect_stdout(sys.stderr):  # the run's own lines; stdout is the table or the JSON
            summary = build.run(cfg)
    except Exception as err:
        error = f"{type(err).__name__}: {err}"
        say(f"chaos: the run failed: {error}")
    finally:
        wall = time.monotonic() - t0
        injector.done.set()
        injector.join_all(timeout_s=180)
        logging.getLogger("orchestrator.trainer").removeHandler(reloads)
    server, faults = injector.server, injector.faults
    try:
        if not server.running():  # the run ended within the outage
            server = start_local_server(backend, artifacts, port=server.port, log_path=server.log_path)
        run_id = json.loads((train_dir / checkpoint.RUN_FILE).read_text())["run_id"]
        status = run_status_and_tags(server.uri, run_id)[0] if run_id else "not created"
        steps = metric_steps(server.uri, run_id, ITERATION_METRIC) if run_id else []
    finally:
        server.stop()
    last = checkpoint.latest(train_dir / "checkpoints")
    iterations = int(last.stem.split("-")[1]) if last else 0
    spool = train_dir / SPOOL_FILE
    spool_left = sum(1 for line in spool.read_text().splitlines() if line.strip()) if spool.exists() else 0
    for f in faults:  # a learner or the replay buffer is back when the trainer reloaded it, too
        if f.target in STATEFUL and f.recovered:
            key = f.target.removeprefix("learner-")
            f.recovered = reloads.keys.count(key) >= sum(g.target == f.target and g.injected for g in faults)
            f.detail += "; the trainer reloaded it" if f.recovered else "; the trainer did not reload it"
    injected = [f for f in faults if f.injected]
    return {
        "benchmark": "chaos",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "config": config,
        "minutes": minutes,
        "kill_every_s": kill_every,
        "outage_s": outage,
        "run_dir": str(run_dir),
        "wall_s": wall,
        "error": error or injector.error,
        "faults": [asdict(f) for f in faults],
        "planned": len(faults),
        "injected": len(injected),
        "recovered": sum(f.recovered for f in injected),
        "ray_restarts": injector.restarts,
        "recoveries": int(summary.get("loop/recoveries", -1)),  # Trainer.recoveries
        "reloads_logged": len(reloads.keys),
        "worker_restarts": int(summary.get("rollout/worker_restarts", -1)),
        "iterations": iterations,
        "metrics_logged": len(set(steps)),
        "metrics_lost": iterations - len(set(steps)),
        "metrics_duplicated": len(steps) - len(set(steps)),
        "spool_left": spool_left,
        "status": status,
        "run_id": run_id,
        "final": {k: float(v) for k, v in summary.items() if k.startswith(("throughput/", "loop/", "eval/"))},
    }


def format_table(result: dict[str, Any]) -> str:
    lines = [
        f"chaos: controlvae on Ray for {result['minutes']:g} min, a rollout worker killed every "
        f"{result['kill_every_s']:g} s, the tracking server down {result['outage_s']:g} s",
        f"  {'at (s)':>7}  {'fault':<6}  {'target':<20}  {'recovered':<14}  how",
    ]
    for f in result["faults"]:
        recovered = ("yes" if f["recovered"] else "NO") if f["injected"] else "(not injected)"
        lines.append(f"  {f['at_s']:7.1f}  {f['kind']:<6}  {f['target']:<20}  {recovered:<14}  {f['detail']}")
    restarts = ", ".join(f"{k} {v}" for k, v in sorted(result["ray_restarts"].items())) or "none"
    lines += [
        f"faults planned {result['planned']}, injected {result['injected']}, recovered {result['recovered']}",
        f"Ray restarts (state API): {restarts}; the trainer reloaded {result['recoveries']} component(s) "
        f"from a checkpoint; worker restarts it counted: {result['worker_restarts']}",
        f"iterations {result['iterations']}; {ITERATION_METRIC} in the server {result['metrics_logged']} "
        f"-> lost {result['metrics_lost']} (duplicated {result['metrics_duplicated']}); "
        f"spool left {result['spool_left']}; MLflow run {result['status']}",
    ]
    if result["error"]:
        lines.append(f"error: {result['error']}")
    return "\n".join(lines)


def passed(result: dict[str, Any]) -> bool:
    """Every fault recovered, no metric lost, the spool empty and the run finished."""
    return (
        result["error"] is None
        and result["injected"] == result["planned"] > 0
        and result["recovered"] == result["injected"]
        and result["metrics_lost"] == 0
        and result["spool_left"] == 0
        and result["status"] == "FINISHED"
    )
