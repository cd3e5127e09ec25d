"""The PPO methods end to end at smoke scale in one process: tracking, evaluation, checkpoints, overlap."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from mlflow.tracking import MlflowClient

from orchestrator.build import build_runtime, run
from orchestrator.tracking.base import NoOpLogger
from orchestrator.trainer import Trainer
from orchestrator.world import load_character_and_library


def test_amp_smoke_run_leaves_a_complete_mlflow_run(smoke):
    cfg = smoke("algo=amp")
    summary = run(cfg)
    assert 0 < summary["eval/pose_error_dtw"] <= summary["eval/pose_error_per_frame"] + 1e-9
    assert 0 < summary["eval/pose_error_eq10"]  # AMP's Eq. 10 as written, beside ours
    client = MlflowClient(f"sqlite:///{cfg.run_dir}/mlflow.db")
    run_id = json.loads((Path(cfg.run_dir) / "run.json").read_text())["run_id"]
    r = client.get_run(run_id)
    assert r.info.status == "FINISHED" and r.data.tags["algo"] == "amp"
    assert r.data.params["algo.discriminator.w_gp"] == "10.0" and "algo.vae.prior" not in r.data.params
    keys = set(r.data.metrics)
    amp = {"disc/reward/style", "disc/reward/task", "disc/reward/total", "disc/accuracy", "disc/input_grad_norm_data"}
    assert {"ppo/episode_return", *amp} <= keys
    eval_files = {a.path for a in client.list_artifacts(run_id, "eval")}
    assert "eval/pose-final.png" in eval_files and "eval/final.json" in eval_files
    assert any(a.path.endswith(".pt") for a in client.list_artifacts(run_id, "checkpoints"))
    steps = [m.step for m in client.get_metric_history(run_id, "ppo/episode_return")]
    assert steps == sorted(steps) and steps[-1] == 6 * 2 * 8 * 16  # iterations x workers x envs x steps


def test_tracker_resumes_from_its_checkpoint(smoke):
    """A resumed tracker run continues from the checkpoint: the same metrics as an uninterrupted run."""
    full = smoke("algo=tracker", "tracking=off", name="full")
    whole = run(full)
    cut = smoke("algo=tracker", "tracking=off", "algo.loop.iterations=3", name="cut")
    run(cut)
    resumed = smoke("algo=tracker", "tracking=off", "resume=true", name="cut")
    again = run(resumed)
    for key in ("ppo/loss", "ppo/return_mean", "eval/pose_error_dtw"):
        assert np.isclose(again[key], whole[key], rtol=1e-5), key


def test_overlap_trains_on_the_batch_collected_one_iteration_earlier(smoke):
    lags = {}
    for overlap in (False, True):
        cfg = smoke("algo=amp", f"algo.loop.overlap={str(overlap).lower()}", "tracking=off", name=str(overlap))
        character, _ = load_character_and_library(cfg)
        rt = build_runtime(cfg)
        trainer = Trainer(cfg, rt, NoOpLogger(), character)
        trainer.method.start(trainer)
        lags[overlap] = [trainer.step()["ppo/policy_lag"] for _ in range(3)]
        trainer.method.finish(trainer)
    assert lags[False] == [0, 0, 0]
    updates = 16 * 8 * 2 // 64  # PPO steps per iteration: samples / minibatch, one epoch
    assert lags[True] == [0, updates, updates]  # the first batch was collected before any update
