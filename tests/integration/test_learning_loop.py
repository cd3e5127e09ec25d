"""The default ControlVAE loop learns: after a short local run the controller tracks the clips
better in the simulator than the untrained one it started from.

This is the whole service's learning test: collection, the replay buffer, both learners,
weight publication and evaluation, at the default run's model and loop settings with fewer
iterations and a smaller evaluation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from orchestrator.build import run
from orchestrator.compose import compose, validate
from orchestrator.world import evaluation_sim_config, load_character_and_library
from workers.evaluation.controller import tracking_error
from workers.learners.vae import build_controller

CONF = Path(__file__).resolve().parents[2] / "conf"

OVERRIDES = [
    "motion=walk",
    "algo.loop.iterations=100",
    "algo.loop.checkpoint_every=0",
    "eval.fall_rollouts=8",
    "eval.fall_max_seconds=5",
    "eval.tracking_seconds=1.0",
    "tracking=embedded",
    "progress=false",
]


@pytest.mark.slow
def test_default_loop_improves_tracking_in_the_simulator(tmp_path):
    cfg = validate(compose([f"run_dir={tmp_path}", *OVERRIDES]))
    character, library = load_character_and_library(cfg)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        untrained = build_controller(character.num_bodies, character.num_actions, cfg.algo.vae)
    before = tracking_error(untrained, library, character, 1.0, evaluation_sim_config(cfg), seed=cfg.seed)["mean"]

    summary = run(cfg)
    after = summary["eval/tracking_error_mean"]
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    (r,) = client.search_runs(client.search_experiments()[0].experiment_id)
    rec = [m.value for m in sorted(client.get_metric_history(r.info.run_id, "vae/rec"), key=lambda m: m.step)]
    wm = [m.value for m in sorted(client.get_metric_history(r.info.run_id, "world_model/loss"), key=lambda m: m.step)]
    print(
        f"tracking error {before:.3f} -> {after:.3f} m; vae/rec {rec[0]:.1f} -> {rec[-1]:.1f}; "
        f"world_model/loss {wm[0]:.3f} -> {wm[-1]:.3f}"
    )
    assert np.isfinite(after)
    # The loop is deterministic on one machine, but its trajectory is not the same on another (a different
    # CPU's floating point): after / before measured 0.67, 0.70, 0.82 for seeds 0, 1, 2 on one machine and
    # 0.87 for seed 0 on another. An untrained or broken loop stays at 1 or above; 0.9 asks for a clear gain.
    # Not every seed passes: on 2026-12-05 seeds 0-3 gave 0.68, 0.70, 0.67 and 1.33 (README, "Learners"), and
    # a float rounding's difference (the losses compiled) moved seed 0 to 0.95. A fixed seed of a chaotic loop.
    # The clip's two segments are a narrow view, too: from 16 start frames spread over it, the same seed-0
    # controller is no better than untrained (1.06; `scripts/learning_seeds.py`, README "Learners").
    assert after < 0.9 * before
    assert np.mean(rec[-5:]) < 0.85 * np.mean(rec[:5])
