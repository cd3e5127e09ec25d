"""ControlVAE's loop as the paper trains it: per-learner update ratios, data balancing and clip switches in
the running loop (local runtime, smoke sizes)."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.compose import compose, validate
from orchestrator.runtime.local import LocalRuntime
from orchestrator.tracking.base import NoOpLogger
from orchestrator.trainer import Trainer
from orchestrator.world import load_character_and_library

ITERATIONS = 12


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("collection")
    cfg = validate(compose([
        "scale=smoke",
        f"run_dir={run_dir}",
        "progress=false",
        "tracking=off",
        "algo.loop.replay_ratio=1",
        "+algo.loop.replay_ratios={world_model: 2, vae: 5}",
        "algo.loop.balance_every=4",
        "algo.loop.switch_rate=1.0",
    ]))  # fmt: skip
    character, library = load_character_and_library(cfg)
    trainer = Trainer(cfg, LocalRuntime(), NoOpLogger(), character)
    trainer.method.start(trainer)
    history = [trainer.step() for _ in range(ITERATIONS)]
    trainer.method.finish(trainer)
    return cfg, library, trainer, history


def test_each_learner_takes_the_updates_its_own_ratio_makes_due(trained):
    cfg, _, trainer, history = trained
    loop, wm, vae = cfg.algo.loop, cfg.algo.world_model, cfg.algo.vae
    per_iteration = cfg.runtime.rollout_workers * cfg.runtime.envs_per_worker * loop.collect_steps
    assert per_iteration >= loop.warmup  # every iteration updates
    collected = per_iteration * ITERATIONS
    # The credit carries over between iterations, so the totals are exact.
    assert history[-1]["loop/world_model_updates"] == int(2 * collected / (wm.batch_size * wm.rollout_steps))
    assert history[-1]["loop/vae_updates"] == int(5 * collected / (vae.batch_size * vae.rollout_steps))
    assert history[-1]["loop/vae_updates"] > 2 * history[-1]["loop/world_model_updates"]
    assert history[-1]["world_model/version"] == history[-1]["loop/world_model_updates"]
    assert history[-1]["vae/version"] == history[-1]["loop/vae_updates"]


def test_balancing_refreshes_the_workers_start_weights(trained):
    cfg, library, trainer, history = trained
    refreshes = [i for i, m in enumerate(history, 1) if "balance/frames_seen" in m]
    assert refreshes == [4, 8, 12]
    values = trainer.method.values
    assert values.refreshes == 3 and (values.values > 0).any()
    for m in (history[i - 1] for i in refreshes):
        shares = [m[f"balance/start_share/{name}"] for name in library.names]
        assert sum(shares) == pytest.approx(1.0)
    # Every rollout worker draws its starts by the new weights, from its next collect on.
    trainer.runtime.get(trainer.collect(1, cfg.algo.loop.staleness))
    for actor in trainer.workers:
        np.testing.assert_allclose(actor.worker.library._frame_weights, values.weights())
    # The learning curve of Eq. 20 and the switches are reported every iteration.
    assert all(0 < m["rollout/reward"] <= 1 for m in history)
    assert sum(m["rollout/switches"] for m in history) > 0
    assert sum(m["rollout/switch_falls"] + m["rollout/switch_recoveries"] for m in history) > 0
    # The values go into checkpoints with the method's counters.
    state = trainer.method.state_dict()
    trainer.method.values = None
    trainer.method.load_state_dict(state)
    np.testing.assert_array_equal(trainer.method.values.values, values.values)
