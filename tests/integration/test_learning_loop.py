"""The default ControlVAE loop learns: after the default run's 200 iterations on the walk clip the
controller tracks it better in the simulator than the untrained one it started from.

This is the whole service's learning test: collection, the replay buffer, both learners,
weight publication and evaluation, at the default run's model and loop settings with one clip
and a smaller evaluation.
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
    "algo.loop.iterations=200",
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
    before = tracking_error(untrained, character, library, 1.0, evaluation_sim_config(cfg), seed=cfg.seed)["mean"]

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
    # CPU's floating point), and a fixed seed of it is one draw. At 100 iterations that draw was a lottery:
    # after / before ranged from 0.37 to 1.33 over seeds 0-7 (2 of 8 eager seeds above 0.9; the losses
    # compiled, a float rounding's difference, moved seed 0 from 0.68 to 0.95), and from 16 start frames
    # spread over the clip seed 0's controller was no better than untrained (1.06). At the default run's 200
    # iterations (`scripts/learning_seeds.py --seeds 0-5 --iterations 200`, 2026-12-06) every run learned:
    # 0.19-0.52 over six seeds, eager and compiled (0.22-0.42 from 16 starts). An untrained or broken loop
    # stays at 1 or above; 0.7 asks for a clear gain with room for another machine's rounding.
    assert after < 0.7 * before
    assert np.mean(rec[-5:]) < 0.85 * np.mean(rec[:5])
