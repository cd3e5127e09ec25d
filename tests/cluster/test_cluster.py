"""The cluster path, with real processes: `python -m orchestrator.cluster up` (a Ray head with 2 logical CPUs and a
node with 4, token authentication on; PostgreSQL; `mlflow server --app-name basic-auth` on it with proxied
artifacts), a training job and a sweep submitted with `ray job submit`, then `down`, which keeps the database and
the jobs' working dirs.

The MLflow server refuses a request without the lab user's password (401), and another user's writes to the lab's
runs (403); the jobs log through it with the credentials that the Ray nodes pass them.

A job's five actors need 4.5 CPUs, more than either node has, and `runtime.placement=SPREAD` asks for every node:
the actors must land on both. What the jobs logged must be in PostgreSQL's tables and under the server's artifact
destination. The placement observed is printed (run with -s to see it) and written to placement-*.json beside the
cluster's state.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import torch

from orchestrator.cluster.procs import http_json, session_members
from orchestrator.tracking import mlflow_auth

pytestmark = [pytest.mark.cluster, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
TRAINING_ACTORS = {"learner-world_model", "learner-vae", "replay", "rollout-0", "rollout-1"}


@dataclass
class Cluster:
    state_dir: Path
    state: dict[str, Any]  # cluster.json
    env: dict[str, str]  # a client's environment (`eval "$(python -m orchestrator.cluster env)"`)
    kept: list[Path]  # what `down` must leave in place (checked after it)

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
        return self.submit_command(name, ["python", "-m", "orchestrator", *args], timeout=timeout)[0]

    def submit_command(
        self, name: str, entrypoint: list[str], options: tuple[str, ...] = (), timeout: float = 420
    ) -> tuple[dict[str, Any], str]:
        """`ray job submit [options] -- <entrypoint>`: (the job's info, its output), asserting that it SUCCEEDED."""
        submission = f"{name}-{uuid.uuid4().hex[:6]}"
        command = [sys.executable, "-m", "ray.scripts.scripts", "job", "submit", "--address", self.dashboard]
        command += ["--submission-id", submission, *options, "--", *entrypoint]
        proc = subprocess.run(command, cwd=ROOT, env=self.env, capture_output=True, text=True, timeout=timeout)
        info = self.rest(f"/api/jobs/{submission}")
        assert info["status"] == "SUCCEEDED", f"{submission}: {info['status']} {info['message']}\n{proc.stdout[-3000:]}"
        assert proc.returncode == 0, proc.stderr[-2000:]
        return info, proc.stdout

    def mlflow(self, method: str, path: str, body: dict | None = None, auth: tuple[str, str] | None = None) -> int:
        """The HTTP status of one REST call to the MLflow server, with basic authentication when `auth` is given."""
        headers = {"Content-Type": "application/json"}
        if auth is not None:
            headers["Authorization"] = "Basic " + base64.b64encode(f"{auth[0]}:{auth[1]}".encode()).decode()
        data = json.dumps(body).encode() if body is not None else None
        request = urllib.request.Request(f"{self.tracking_uri}{path}", data=data, headers=headers, method=method)
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                return response.status
        except urllib.error.HTTPError as e:
            return e.code

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
        exports = cluster_command("env", "--state-dir", str(state_dir)).stdout
        env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_AUTH_TOKEN")}
        env = {k: v for k, v in env.items() if not k.startswith("MLFLOW_TRACKING_")}
        # What a user's shell gets from eval "$(python -m orchestrator.cluster env)".
        shell = subprocess.run(["sh", "-c", 'eval "$1" && env -0', "sh", exports], env=env, capture_output=True)
        client = dict(item.split("=", 1) for item in shell.stdout.decode().split("\0") if "=" in item)
        assert client["MLFLOW_TRACKING_USERNAME"] == "lab" and client["MLFLOW_TRACKING_PASSWORD"]
        kept = [Path(state["postgres"]["data_dir"]) / "PG_VERSION"]
        yield Cluster(state_dir, state, client, kept)
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
        # The database stays (wherever it lives), and so do the jobs' working dirs in Ray's temp dir.
        if recorded.get("postgres", {}).get("data_dir"):
            data = Path(recorded["postgres"]["data_dir"])
            assert (data / "PG_VERSION").exists() and any((data / "base").iterdir()), data
        if "kept" in locals():
            missing = [str(p) for p in kept if not p.exists()]
            assert not missing, missing
        # What down kept outside the test's state dir (under /tmp) is this test's own: removed here.
        for pointer in ("postgres-home", "ray-temp-dir"):
            if (state_dir / pointer).exists():
                shutil.rmtree((state_dir / pointer).read_text().strip(), ignore_errors=True)


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


def test_the_mlflow_server_refuses_requests_without_the_lab_users_password(cluster, monkeypatch):
    lab = (cluster.env["MLFLOW_TRACKING_USERNAME"], cluster.env["MLFLOW_TRACKING_PASSWORD"])
    search = "/api/2.0/mlflow/experiments/search?max_results=1"
    create = {"name": f"auth-{uuid.uuid4().hex[:6]}"}
    assert cluster.mlflow("GET", search) == 401
    assert cluster.mlflow("POST", "/api/2.0/mlflow/experiments/create", create) == 401
    assert cluster.mlflow("GET", search, auth=(lab[0], "wrong-password")) == 401
    assert cluster.mlflow("GET", "/health") == 200  # the only open route (health checks)
    assert cluster.mlflow("GET", search, auth=lab) == 200
    assert cluster.mlflow("POST", "/api/2.0/mlflow/experiments/create", create, auth=lab) == 200
    # Another authenticated user reads the lab's runs but cannot write to them (default_permission READ).
    admin_password = Path(cluster.state["mlflow"]["admin_password_file"]).read_text().strip()
    mlflow_auth.ensure_user(cluster.tracking_uri, admin_password, "other", "other-password-0123456789")
    other = ("other", "other-password-0123456789")
    import mlflow.tracking

    monkeypatch.setenv("MLFLOW_TRACKING_USERNAME", lab[0])
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", lab[1])
    client = mlflow.tracking.MlflowClient(cluster.tracking_uri)
    run_id = client.create_run(client.get_experiment_by_name(create["name"]).experiment_id).info.run_id
    assert cluster.mlflow("GET", f"/api/2.0/mlflow/runs/get?run_id={run_id}", auth=other) == 200
    tag = {"run_id": run_id, "key": "stage_hash", "value": "forged"}
    assert cluster.mlflow("POST", "/api/2.0/mlflow/runs/set-tag", tag, auth=other) == 403
    assert cluster.mlflow("POST", "/api/2.0/mlflow/runs/set-tag", tag) == 401
    assert cluster.mlflow("POST", "/api/2.0/mlflow/runs/set-tag", tag, auth=lab) == 200


def test_a_working_dir_job_runs_and_writes_under_rays_temp_dir(cluster, tmp_path):
    """`ray job submit --working-dir DIR`: Ray unpacks DIR under its temp dir and runs the job there, so what the
    job writes to relative paths (Hydra's outputs/) lands there; `down` must leave it."""
    (tmp_path / "job").mkdir()
    script = "import os, pathlib; p = pathlib.Path('outputs/x.txt'); p.parent.mkdir(); p.write_text('out'); "
    script += "print('CWD', os.getcwd()); print('USER', os.environ.get('MLFLOW_TRACKING_USERNAME'))"
    (tmp_path / "job" / "job.py").write_text(script)
    _, out = cluster.submit_command("workdir", ["python", "job.py"], ("--working-dir", str(tmp_path / "job")))
    cwd = Path(next(line.split(" ", 1)[1] for line in out.splitlines() if line.startswith("CWD ")))
    assert cwd.is_relative_to(Path(cluster.state["ray"]["temp_dir"]).resolve()) or cwd.is_relative_to(
        cluster.state["ray"]["temp_dir"]
    ), cwd
    assert "USER lab" in out  # the Ray nodes hand the lab's MLflow user to every job
    assert (cwd / "outputs" / "x.txt").read_text() == "out"
    cluster.kept.append(cwd / "outputs" / "x.txt")
    _, out = cluster.submit_command("cwd", ["python", "-c", "import os; print('CWD', os.getcwd())"])
    print(f"\njob cwd with --working-dir: {cwd}; without: {out.split('CWD ', 1)[1].splitlines()[0]}")


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
    weights = torch.load(stored / "weights" / "controller.pt", weights_only=True)  # beside the pickled model
    assert weights and all(isinstance(v, torch.Tensor) for v in weights.values())
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


@pytest.mark.parametrize("key", ["learner_gpus", "worker_gpus"])
def test_a_gpu_the_cluster_does_not_have_is_refused_before_anything_is_written(cluster, tmp_path, key):
    """The cluster has no GPU: asking one for each learner, or for each rollout worker (whatever the simulator
    engine: the share is reserved), is one line naming the key and what the cluster has, before an MLflow run is
    made or the run directory is written (Ray would wait for it without end)."""
    address = cluster.state["ray"]["head"]["gcs_address"]
    args = [f"runtime.address={address}", f"runtime.{key}=1", f"tracking.uri={cluster.tracking_uri}"]
    args += ["runtime=ray", "scale=smoke", "motion=walk", "progress=false", f"run_dir={tmp_path / 'run'}"]
    args += ["tracking.experiment=gpu-refusal"]
    proc = subprocess.run(
        [sys.executable, "-m", "orchestrator", *args], cwd=tmp_path, env=cluster.env, capture_output=True, text=True
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
    assert lines[0] == f"config error: runtime.{key}=1: the Ray cluster at runtime.address={address} has 0 GPU(s)"
    assert not (tmp_path / "run").exists()
    with cluster.db() as cur:
        cur.execute("SELECT count(*) FROM experiments WHERE name = 'gpu-refusal'")
        assert cur.fetchone()[0] == 0
