"""PhysicsVAE's offline learning-rate schedule as the stage runs it: ×0.7 every 50 epochs (Table 2), epoch by
epoch through the actor's own `train_epoch`, for the simulation layer and the VAE alike."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from orchestrator.components.physicsvae import PhysicsVAEActor, SimulationLayerActor
from orchestrator.compose import compose, validate
from workers.demos import DemoSet
from workers.learners.world_model import build_world_model
from workers.models.body_state import pack


def walk_demos(walk_run, episodes: int = 4, length: int = 12) -> DemoSet:
    """Reference states of the walk as expert episodes, with zero actions (the schedule needs no expert)."""
    out = []
    for e in range(episodes):
        frames = e + np.arange(length + 1)
        states = pack(walk_run.state(np.zeros(length + 1, int), frames)).astype(np.float32)
        out.append({"states": states, "actions": np.zeros((length, 28), np.float32), "clip": 0, "rollout": e,
                    "fell": False, "tracking_error": 0.0})  # fmt: skip
    return DemoSet.from_episodes(out)


def small(algo: str, tmp_path, **section):
    cfg = validate(compose([f"run_dir={tmp_path}", f"algo={algo}", "scale=paper"]))
    assert (cfg.algo.offline.lr_decay, cfg.algo.offline.decay_every) == (0.7, 50)  # Table 2 at scale=paper
    offline = dataclasses.replace(cfg.algo.offline, holdout_rollouts=1)
    parts = {k: dataclasses.replace(getattr(cfg.algo, k), **v) for k, v in section.items()}
    return dataclasses.replace(cfg, algo=dataclasses.replace(cfg.algo, offline=offline, **parts))


@pytest.mark.parametrize("algo", ["simulation_layer", "physicsvae"])
def test_the_learning_rate_falls_by_0_7_every_50_epochs(walk_run, tmp_path, algo):
    demos = walk_demos(walk_run)
    if algo == "simulation_layer":
        cfg = small(algo, tmp_path, world_model={"hidden": (8,), "batch_size": 64})
        actor = SimulationLayerActor(cfg, demos, 15, 28)
        base = cfg.algo.world_model.lr
    else:
        cfg = small(algo, tmp_path, vae={"encoder_hidden": (8,), "policy_hidden": (8,), "batch_size": 64, "alpha": 0.0})
        wm = small("simulation_layer", tmp_path, world_model={"hidden": (8,)}).algo.world_model
        layer = build_world_model(15, 28, wm, 1 / 30).state_dict()
        actor = PhysicsVAEActor(cfg, demos, 15, 28, (wm, layer))
        base = cfg.algo.vae.lr
    seen = []
    torch.manual_seed(0)
    for _ in range(151):
        actor.train_epoch()
        seen.append(actor.learner.optimizer.param_groups[0]["lr"])
    # Epochs 0-49 at the base rate, 50-99 at 0.7 of it, 100-149 at 0.49, epoch 150 at 0.343.
    assert seen[0] == seen[49] == pytest.approx(base)
    assert seen[50] == seen[99] == pytest.approx(0.7 * base)
    assert seen[100] == pytest.approx(0.49 * base) and seen[150] == pytest.approx(0.343 * base)
    assert actor.epoch == 151


def test_a_regress_layer_trains_and_physicsvae_learns_through_it(walk_run, tmp_path):
    """world_model.kind=regress (Table 2's layer): the stage's actor trains it on the demos and reports its
    held-out feature error; a PhysicsVAE with α > 0 takes its α term through the layer's s′ and reports
    heldout_sim_error without body positions (a regressor has none); ControlVAE cannot roll it out."""
    from workers.learners.vae import ControlVAEObjective, VAELearner

    demos = walk_demos(walk_run, episodes=6)
    regress = {"kind": "regress", "hidden": (32,), "activation": "relu", "batch_size": 32}
    cfg = small("simulation_layer", tmp_path, world_model=regress)
    torch.manual_seed(0)
    layer = SimulationLayerActor(cfg, demos, 15, 28)
    before = layer.validate()["heldout_feature_mse_1"]
    for _ in range(20):
        layer.train_epoch()
    assert layer.validate()["heldout_feature_mse_1"] < before
    vae = {"encoder_hidden": (8,), "policy_hidden": (8,), "batch_size": 32, "alpha": 1e-2}
    pv = small("physicsvae", tmp_path, vae=vae)
    actor = PhysicsVAEActor(pv, demos, 15, 28, (cfg.algo.world_model, layer.learner.model.state_dict()))
    metrics = actor.train_epoch()
    assert metrics["sim"] > 0 and metrics["skipped_updates"] == 0  # the α term, through the layer's s′
    out = actor.validate()
    assert out["heldout_sim_error"] > 0 and "heldout_next_pos_error" not in out
    with pytest.raises(ValueError, match="integrating world model"):
        VAELearner(
            15, 28, ControlVAEObjective(encoder_hidden=(8,), policy_hidden=(8,)), world_model=layer.learner.model
        )


def _twins(walk_run, tmp_path, **offline):
    """A regress layer's actor and a PhysicsVAE actor (α > 0, through that layer), seeded alike."""
    demos = walk_demos(walk_run, episodes=6)
    regress = {"kind": "regress", "hidden": (32,), "activation": "relu", "batch_size": 32}
    cfg = small("simulation_layer", tmp_path, world_model=regress)
    cfg = dataclasses.replace(
        cfg, algo=dataclasses.replace(cfg.algo, offline=dataclasses.replace(cfg.algo.offline, **offline))
    )
    torch.manual_seed(0)
    layer = SimulationLayerActor(cfg, demos, 15, 28)
    pv = small(
        "physicsvae", tmp_path, vae={"encoder_hidden": (8,), "policy_hidden": (8,), "batch_size": 32, "alpha": 1e-2}
    )
    pv = dataclasses.replace(
        pv, algo=dataclasses.replace(pv.algo, offline=dataclasses.replace(pv.algo.offline, **offline))
    )
    torch.manual_seed(0)
    vae = PhysicsVAEActor(pv, demos, 15, 28, (cfg.algo.world_model, layer.learner.model.state_dict()))
    return layer, vae


def test_the_features_computed_once_give_the_updates_computed_per_batch(walk_run, tmp_path):
    """Each offline actor computes s of the whole dataset once and hands each batch its windows' rows: the
    layer's and the VAE's updates are those the learners make from the body states themselves (to float
    rounding), for the normaliser, the encoder and the layer's input alike."""
    for actor in _twins(walk_run, tmp_path):
        starts = actor.rng.choice(actor.train_starts, size=actor.batch_size)
        batch = actor.batch(starts)
        assert batch.features is not None
        twin = type(batch)(**{**vars(batch), "features": None})
        torch.manual_seed(1)
        learner = actor.learner
        state = {k: v.clone() for k, v in learner.module.state_dict().items()}
        opt = learner.optimizer.state_dict()
        if hasattr(learner, "generator"):
            gen = learner.generator.get_state()
        first = learner.update(batch)
        after = {k: v.clone() for k, v in learner.module.state_dict().items()}
        learner.module.load_state_dict(state)
        learner.optimizer.load_state_dict(opt)
        if hasattr(learner, "generator"):
            learner.generator.set_state(gen)
        second = learner.update(twin)
        assert first == pytest.approx(second, rel=1e-5, abs=1e-7)
        for k, v in learner.module.state_dict().items():
            torch.testing.assert_close(v, after[k], rtol=1e-5, atol=1e-6)


def test_bfloat16_updates_keep_float32_weights_and_stay_close(walk_run, tmp_path):
    """algo.offline.precision=bfloat16: an epoch's matmuls in bfloat16 under autocast, the weights and the
    optimiser in float32; its losses are not float32's (it changes the numbers: hence its paired study) but
    within a few per cent of them after one epoch from the same start."""
    plain = [a.train_epoch() for a in _twins(walk_run, tmp_path / "fp32")]
    low = _twins(walk_run, tmp_path / "bf16", precision="bfloat16")
    half = [a.train_epoch() for a in low]
    for a in low:
        assert {p.dtype for p in a.learner.module.parameters()} == {torch.float32}
    for f, b in zip(plain, half, strict=True):
        assert b["loss"] != f["loss"] and b["loss"] == pytest.approx(f["loss"], rel=0.05)
