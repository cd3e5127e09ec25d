"""Methods on the MuJoCo Warp simulator (`sim.backend=warp`, Warp's CPU device) end to end at smoke scale, in one
process: the method's module unchanged, the run logged to MLflow and evaluated on the same engine.

The first Warp step on a machine compiles MuJoCo Warp's kernels (tens of seconds; cached afterwards), and a
run takes about half a minute on two cores, hence `slow`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from orchestrator.build import run

pytest.importorskip("mujoco_warp")


def finished_run(cfg):
    client = MlflowClient(f"sqlite:///{cfg.run_dir}/mlflow.db")
    run_id = json.loads((Path(cfg.run_dir) / "run.json").read_text())["run_id"]
    r = client.get_run(run_id)
    assert r.info.status == "FINISHED"
    assert r.data.params["sim.backend"] == "warp" and r.data.params["sim.device"] == "cpu"
    return client, run_id, r


@pytest.mark.slow
@pytest.mark.parametrize(
    ("algo", "learned", "evaluated"),
    [
        ("tracker", "ppo/loss", ("eval/pose_error_dtw", "eval/pose_error_per_frame")),
        ("controlvae", "vae/rec", ("eval/time_until_fall_mean", "eval/tracking_error_mean")),
    ],
)
def test_a_method_runs_on_the_warp_simulator_and_is_evaluated_there(smoke, algo, learned, evaluated):
    cfg = smoke(f"algo={algo}", "sim.backend=warp", "runtime=local", "motion=walk")
    summary = run(cfg)
    client, run_id, r = finished_run(cfg)
    assert r.data.tags["algo"] == algo
    history = client.get_metric_history(run_id, learned)
    assert len(history) == cfg.algo.loop.iterations and all(np.isfinite(m.value) for m in history)
    for key in evaluated:  # evaluated on MuJoCo Warp too: finite, positive errors and times
        assert np.isfinite(summary[key]) and summary[key] > 0, key
    assert "eval/final.json" in {a.path for a in client.list_artifacts(run_id, "eval")}
