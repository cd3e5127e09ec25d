"""The smoke preset end to end in one process: tracking, checkpoints, determinism, resume."""

from __future__ import annotations

import json

import mlflow
import mlflow.pytorch
import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from orchestrator.build import run
from workers.body.character import Character
from workers.body.features import StateLayout


def client_for(cfg) -> MlflowClient:
    return MlflowClient(f"sqlite:///{cfg.run_dir}/mlflow.db")


def run_id_of(cfg) -> str:
    with open(f"{cfg.run_dir}/run.json") as f:
        return json.load(f)["run_id"]


def test_smoke_run_leaves_a_complete_mlflow_run(smoke, capsys):
    cfg = smoke("tracking.system_metrics_s=0.5")
    summary = run(cfg)
    assert np.isfinite(summary["eval/time_until_fall_mean"])
    client = client_for(cfg)
    r = client.get_run(run_id_of(cfg))
    assert r.info.status == "FINISHED"
    assert r.data.params["algo.vae.prior"] == "conditional" and r.data.params["seed"] == "0"
    assert r.data.tags["preset"] == "default" and r.data.tags["algo"] == "controlvae"
    # The MLflow UI opens the experiment on its model-training view.
    assert client.get_experiment(r.info.experiment_id).tags["mlflow.experimentKind"] == "custom_model_development"
    assert {"eval/random_sampling_fell", "eval/random_sampling_distance", "rollout/reward"} <= set(r.data.metrics)
    keys = set(r.data.metrics)
    assert {"eval/time_until_fall_mean", "eval/tracking_error_mean", "throughput/samples_per_s"} <= keys
    assert any(k.startswith("world_model/") for k in keys) and any(k.startswith("vae/") for k in keys)
    artifacts = {a.path for a in client.list_artifacts(r.info.run_id)}
    assert "config.json" in artifacts
    assert any(a.path.endswith(".pt") for a in client.list_artifacts(r.info.run_id, "checkpoints"))
    assert any(a.path.endswith(".png") for a in client.list_artifacts(r.info.run_id, "eval"))
    history = client.get_metric_history(r.info.run_id, "throughput/samples_per_s")
    steps = [m.step for m in history]
    assert steps == sorted(steps) and steps[-1] == 12 * 2 * 8 * 16  # iterations x workers x envs x steps
    # The untrained policy is evaluated first (step 0): the curves start there.
    assert [m.step for m in client.get_metric_history(r.info.run_id, "eval/time_until_fall_mean")] == [0, steps[-1]]
    # System metrics under MLflow's names (its UI's "System metrics" tab).
    assert {"system/cpu_utilization_percentage", "system/system_memory_usage_megabytes"} <= keys
    # The trained controller as an MLflow model that loads and acts: z at the prior's mean, so deterministic.
    model_uri = r.data.tags["model_uri"]
    mlflow.set_tracking_uri(f"sqlite:///{cfg.run_dir}/mlflow.db")
    model = mlflow.pytorch.load_model(model_uri)
    example = np.asarray(mlflow.models.Model.load(model_uri).load_input_example(), np.float32)
    with torch.no_grad():
        a, b = model(torch.from_numpy(example)), model(torch.from_numpy(example))
    character = Character.load()
    assert a.shape == (1, character.num_actions) and torch.equal(a, b) and torch.isfinite(a).all()
    spec = mlflow.models.get_model_info(model_uri).signature.inputs.to_dict()[0]["tensor-spec"]
    assert list(spec["shape"]) == [-1, StateLayout(character.num_bodies).dim]
    # The closing summary: the table beside the untrained policy, and where to look.
    out = capsys.readouterr().out
    assert "untrained" in out and "time_until_fall_mean" in out and model_uri in out and "mlflow ui" in out


def metric_values(cfg, keys):
    client = client_for(cfg)
    rid = run_id_of(cfg)
    return {k: [(m.step, m.value) for m in client.get_metric_history(rid, k)] for k in keys}


def test_two_local_runs_with_one_seed_agree(smoke):
    short = ("algo.loop.iterations=6", "algo.loop.checkpoint_every=0")
    a, b = smoke(*short, name="a"), smoke(*short, name="b")
    run(a)
    run(b)
    keys = ["world_model/loss", "vae/rec", "vae/kl", "eval/time_until_fall_mean", "eval/tracking_error_mean"]
    va, vb = metric_values(a, keys), metric_values(b, keys)
    assert all(va[k] for k in keys)
    assert va == vb


def test_resume_continues_the_same_run(smoke):
    first = smoke("algo.loop.iterations=4", "algo.loop.checkpoint_every=2", name="r")
    run(first)
    rid = run_id_of(first)
    resumed = smoke("algo.loop.iterations=8", "algo.loop.checkpoint_every=2", "resume=true", name="r")
    run(resumed)
    assert run_id_of(resumed) == rid
    history = client_for(first).get_metric_history(rid, "throughput/samples_per_s")
    steps = [m.step for m in history]
    per_iteration = 2 * 8 * 16
    assert steps == [per_iteration * i for i in range(1, 9)]
    assert client_for(first).get_run(rid).info.status == "FINISHED"


@pytest.mark.slow
def test_unreachable_tracking_server_does_not_stop_training(smoke, tmp_path):
    from orchestrator.tracking.mlflow import replay_spool
    from orchestrator.tracking.server import free_port, start_local_server

    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    cfg = smoke(f"tracking.uri={uri}", "algo.loop.iterations=4", "algo.loop.checkpoint_every=0")
    summary = run(cfg)  # nothing listens on the port: training goes on, metrics go to the spool
    assert np.isfinite(summary["eval/time_until_fall_mean"])
    spool = tmp_path / "run" / "tracking-spool.jsonl"
    assert spool.exists() and spool.stat().st_size > 0
    with start_local_server(f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "server-artifacts", port=port):
        assert replay_spool(cfg.run_dir, uri) == 0
        client = MlflowClient(uri)
        runs = client.search_runs([client.get_experiment_by_name("default").experiment_id])
        assert len(runs) == 1
        history = client.get_metric_history(runs[0].info.run_id, "throughput/samples_per_s")
        assert [m.step for m in history] == [2 * 8 * 16 * i for i in range(1, 5)]
        assert runs[0].info.status == "FINISHED"
