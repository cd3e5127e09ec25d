"""The cluster path, with real processes: `python -m orchestrator.cluster up` (a Ray head with 2 logical CPUs and a
node with 4, token authentication on; PostgreSQL; `mlflow server` on it with proxied artifacts), a training job and a
sweep submitted with `ray job submit`, then `down`.

A job's five actors need 4.5 CPUs, more than either node has, and `runtime.placement=SPREAD` asks for every node:
the actors must land on both. What the jobs logged must be in PostgreSQL's tables and under the server's artifact
destination. The placement observed is printed (run with -s to see it) and written to placement-*.json beside the
cluster's state.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.error
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from orchestrator.cluster.procs import http_json, session_members

pytestmark = [pytest.mark.cluster, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
TRAINING_ACTORS = {"learner-world_model", "learner-vae", "replay", "rollout-0", "rollout-1"}


@dataclass
class Cluster:
    state_dir: Path
    state: dict[str, Any]  # cluster.json
    env: dict[str, str]  # a client's environment (`python -m orchestrator.cluster env`)

    @property
    def dashboard(self) -> str:
        return self.state["ray"]["head"]["dashboard_url"]

    @property
    def token(self) -> str:
        return Path(self.state["ray"]["auth_token_path"]).read_text()

    @property
    def tracking_uri(self) -> str:
        return self.state["mlflow"]["uri"]

    def node_ids(self) -> set[str]:
        return {self.state["ray"]["head"]["node_id"], *(n["node_id"] for n in self.state["ray"]["nodes"])}

    def rest(self, path: str) -> Any:
        return http_json(f"{self.dashboard}{path}", self.token, timeout=30)

    def actors(self) -> list[dict[str, Any]]:
        return self.rest("/api/v0/actors?limit=10000&detail=true")["data"]["result"]["result"]

    def submit(self, name: str, *args: str, timeout: float = 420) -> dict[str, Any]:
        """`ray job submit` of `python -m orchestrator <args>` (its python: the one that started the cluster, first
        on the nodes' PATH); returns the job's info once it ended, asserting that it SUCCEEDED."""
        submission = f"{name}-{uuid.uuid4().hex[:6]}"
        command = [sys.executable, "-m", "ray.scripts.scripts", "job", "submit", "--address", self.dashboard]
        command += ["--submission-id", submission, "--", "python", "-m", "orchestrator", *args]
        proc = subprocess.run(command, cwd=ROOT, env=self.env, capture_output=True, text=True, timeout=timeout)
        info = self.rest(f"/api/jobs/{submission}")
        assert info["status"] == "SUCCEEDED", f"{submission}: {info['status']} {info['message']}\n{proc.stdout[-3000:]}"
        assert proc.returncode == 0, proc.stderr[-2000:]
        return info

    @contextmanager
    def db(self):
        """A cursor on the MLflow database, as the server's own role."""
        import psycopg2

        pg = self.state["postgres"]
        conn = psycopg2.connect(pg["uri"], password=Path(pg["password_file"]).read_text().strip())
        try:
            with conn.cursor() as cur:
                yield cur
        finally:
            conn.close()


def cluster_command(*args: str, timeout: float = 420) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "orchestrator.cluster", *args]
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    state_dir = tmp_path_factory.mktemp("cluster")
    started = time.monotonic()
    try:
        up = cluster_command("up", "--state-dir", str(state_dir), "--json", "--timeout", "180")
        assert up.returncode == 0, up.stderr[-2000:]
        print(f"\ncluster up in {time.monotonic() - started:.0f} s")
        info = json.loads(up.stdout)
        state = json.loads((state_dir / "cluster.json").read_text())
        assert info["ray_dashboard"].startswith("http://127.0.0.1:") and info["mlflow_tracking_uri"].startswith(
            "http://127.0.0.1:"
        )
        assert [n["cpus"] for n in info["ray_nodes"]] == [2, 4] and len({n["node_id"] for n in info["ray_nodes"]}) == 2
        exports = cluster_command("env", "--state-dir", str(state_dir)).stdout.splitlines()
        client = dict(line.removeprefix("export ").split("=", 1) for line in exports)
        env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_AUTH_TOKEN")}
        yield Cluster(state_dir, state, {**env, **client})
    finally:
        recorded = json.loads((state_dir / "cluster.json").read_text()) if (state_dir / "cluster.json").exists() else {}
        down = cluster_command("down", "--state-dir", str(state_dir), timeout=180)
        assert down.returncode == 0, down.stderr
        # Every process that up started is gone (each was the leader of its own session), and so is the database.
        leaders = [
            recorded.get("mlflow"),
            *recorded.get("ray", {}).get("nodes", []),
            recorded.get("ray", {}).get("head"),
        ]
        assert not [p.pid for r in leaders if r for p in session_members(r)]
        assert not (Path(recorded.get("postgres", {}).get("data_dir", state_dir)) / "postmaster.pid").exists()
        assert cluster_command("status", "--state-dir", str(state_dir)).returncode == 1


def placement(cluster: Cluster, actors: list[dict[str, Any]], name: str) -> dict[str, str]:
    """{actor name: 'head' | 'node-1'}, printed and written to placement-<name>.json."""
    label = {cluster.state["ray"]["head"]["node_id"]: "head"}
    label.update({n["node_id"]: f"node-{i}" for i, n in enumerate(cluster.state["ray"]["nodes"], start=1)})
    where = {f"{a['name']} ({a['ray_namespace']})": label.get(a["node_id"], a["node_id"]) for a in actors}
    (cluster.state_dir / f"placement-{name}.json").write_text(json.dumps(where, indent=2, sort_keys=True))
    print(f"\n{name} placement: {json.dumps(where, sort_keys=True)}")
    return where


def test_token_authentication_is_on(cluster):
    with pytest.raises(urllib.error.HTTPError) as refused:
        http_json(f"{cluster.dashboard}/api/jobs/")
    assert refused.value.code == 401
    with pytest.raises(urllib.error.HTTPError) as wrong:
        http_json(f"{cluster.dashboard}/api/jobs/", token="0" * 64)
    assert wrong.value.code == 403
    assert isinstance(cluster.rest("/api/jobs/"), list)


def test_a_training_job_spreads_its_actors_over_both_nodes_and_tracks_into_postgres(cluster, tmp_path):
    started = time.monotonic()
    args = ["runtime=ray", "runtime.address=auto", "runtime.placement=SPREAD", f"tracking.uri={cluster.tracking_uri}"]
    args += ["scale=smoke", "motion=walk", "progress=false", f"hydra.run.dir={tmp_path / 'run'}"]
    job = cluster.submit("train", *args)
    print(f"\ntraining job in {time.monotonic() - started:.0f} s")
    actors = [a for a in cluster.actors() if a["job_id"] == job["job_id"]]
    assert {a["name"] for a in actors} == TRAINING_ACTORS
    where = placement(cluster, actors, "train")
    assert {a["node_id"] for a in actors} == cluster.node_ids(), where  # both nodes, and only this cluster's

    with cluster.db() as cur:
        cur.execute(
            "SELECT r.run_uuid, r.status, r.artifact_uri, r.experiment_id FROM runs r "
            "JOIN tags t ON t.run_uuid = r.run_uuid WHERE t.key = 'algo' AND t.value = 'controlvae'"
        )
        runs = cur.fetchall()
        assert len(runs) == 1, runs
        run_id, status, artifact_uri, experiment_id = runs[0]
        assert status == "FINISHED" and artifact_uri == f"mlflow-artifacts:/{experiment_id}/{run_id}/artifacts"
        cur.execute("SELECT key, value FROM params WHERE run_uuid = %s", (run_id,))
        params = dict(cur.fetchall())
        assert params["runtime.placement"] == "SPREAD" and params["runtime.address"] == "auto"
        assert params["algo.name"] == "controlvae" and params["scale_name"] == "smoke"
        cur.execute("SELECT DISTINCT key FROM metrics WHERE run_uuid = %s", (run_id,))
        metrics = {k for (k,) in cur.fetchall()}
        assert {"world_model/loss", "vae/rec", "eval/time_until_fall_mean", "throughput/samples_per_s"} <= metrics
        cur.execute("SELECT max(step) FROM metrics WHERE run_uuid = %s AND key = 'world_model/loss'", (run_id,))
        assert cur.fetchone()[0] > 0  # steps are samples collected

    # Artifacts went through the server's proxy into its destination, not into the job's directory.
    stored = Path(cluster.state["mlflow"]["artifacts"]) / str(experiment_id) / run_id / "artifacts"
    files = {p.relative_to(stored).as_posix() for p in stored.rglob("*") if p.is_file()}
    assert {"config.json", "eval/final.json", "hydra/config.yaml"} <= files, sorted(files)
    assert any(f.startswith("checkpoints/ckpt-") and f.endswith(".pt") for f in files), sorted(files)
    assert json.loads((stored / "config.json").read_text())["runtime"]["placement"] == "SPREAD"
    assert not (tmp_path / "run" / "mlruns").exists()


def test_a_sweep_on_the_cluster_puts_its_parent_and_children_in_postgres(cluster, tmp_path):
    """The gradient-penalty preset, cut to two of its four penalties (the four take about 4.5 min on a busy
    two-core machine), without videos and model logging; the parent run gets the preset's comparison."""
    before = {a["actor_id"] for a in cluster.actors()}
    sweep_dir = tmp_path / "sweep"
    started = time.monotonic()
    args = ["+experiment=ablation_gp", "scale=smoke", "runtime=ray", "runtime.address=auto", "runtime.placement=SPREAD"]
    args += [f"tracking.uri={cluster.tracking_uri}", "progress=false", "eval.video=false", "tracking.log_model=false"]
    args += ["algo.discriminator.w_gp=0,10", f"hydra.sweep.dir={sweep_dir}", "-m"]
    cluster.submit("sweep", *args)
    print(f"\nsweep job in {time.monotonic() - started:.0f} s")
    parent_id = json.loads((sweep_dir / "sweep.json").read_text())["parent_run_id"]

    actors = [
        a for a in cluster.actors() if a["actor_id"] not in before and a["name"] and "mocap-" in a["ray_namespace"]
    ]
    assert {a["name"] for a in actors} == {"learner-ppo", "learner-discriminator", "rollout-0", "rollout-1"}
    assert len({a["ray_namespace"] for a in actors}) == 2  # one Ray connection per point
    where = placement(cluster, actors, "sweep")
    assert {a["node_id"] for a in actors} == cluster.node_ids(), where

    with cluster.db() as cur:
        cur.execute("SELECT status, experiment_id FROM runs WHERE run_uuid = %s", (parent_id,))
        status, experiment_id = cur.fetchone()
        assert status == "FINISHED"
        cur.execute("SELECT name FROM experiments WHERE experiment_id = %s", (experiment_id,))
        assert cur.fetchone()[0] == "ablation_gp"
        cur.execute("SELECT value FROM tags WHERE run_uuid = %s AND key = 'sweep_id'", (parent_id,))
        assert cur.fetchone()[0] == parent_id
        cur.execute(
            "SELECT r.run_uuid, r.status, p.value FROM runs r JOIN tags t ON t.run_uuid = r.run_uuid "
            "JOIN params p ON p.run_uuid = r.run_uuid AND p.key = 'algo.discriminator.w_gp' "
            "WHERE t.key = 'mlflow.parentRunId' AND t.value = %s",
            (parent_id,),
        )
        children = cur.fetchall()
        assert sorted(float(w) for _, _, w in children) == [0.0, 10.0]
        assert {s for _, s, _ in children} == {"FINISHED"}
        cur.execute(
            "SELECT count(DISTINCT run_uuid) FROM metrics WHERE key = 'eval/pose_error_dtw' AND run_uuid = ANY(%s)",
            ([c[0] for c in children],),
        )
        assert cur.fetchone()[0] == 2

    stored = Path(cluster.state["mlflow"]["artifacts"]) / str(experiment_id) / parent_id / "artifacts"
    assert {"comparison.md", "comparison.json", "comparison.png"} <= {p.name for p in stored.iterdir()}
    assert "| 10.0 | 1 |" in (stored / "comparison.md").read_text()


def test_a_gpu_the_cluster_does_not_have_is_refused_before_anything_is_written(cluster, tmp_path):
    """The cluster has no GPU: asking one for each learner is one line naming the key and what the cluster has,
    before an MLflow run is made or the run directory is written (Ray would wait for it without end)."""
    address = cluster.state["ray"]["head"]["gcs_address"]
    args = [f"runtime.address={address}", "runtime.learner_gpus=1", f"tracking.uri={cluster.tracking_uri}"]
    args += ["runtime=ray", "scale=smoke", "motion=walk", "progress=false", f"run_dir={tmp_path / 'run'}"]
    args += ["tracking.experiment=gpu-refusal"]
    proc = subprocess.run(
        [sys.executable, "-m", "orchestrator", *args], cwd=tmp_path, env=cluster.env, capture_output=True, text=True
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
    assert (
        lines[0] == f"config error: runtime.learner_gpus=1: the Ray cluster at runtime.address={address} has 0 GPU(s)"
    )
    assert not (tmp_path / "run").exists()
    with cluster.db() as cur:
        cur.execute("SELECT count(*) FROM experiments WHERE name = 'gpu-refusal'")
        assert cur.fetchone()[0] == 0
