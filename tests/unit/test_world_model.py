"""The world model's loss, normalisation and learner mechanics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from workers.learners.base import NonFiniteWeightsError, Schedule
from workers.learners.world_model import WorldModelBatch, WorldModelConfig, WorldModelLearner, build_world_model
from workers.losses.world_model import world_model_loss
from workers.models import body_state as B
from workers.models.world_model import WorldModel


def test_loss_known_answer():
    # One body: position off by (0.3, 0, 0) → mean |error| over 3 coordinates = 0.1; identical rotations;
    # linear velocity off by 0.6 in one coordinate → 0.2; angular velocity equal.
    a = torch.zeros(1, 1, 1, 13)
    a[..., 3] = 1.0
    b = a.clone()
    b[..., 0] = 0.3
    b[..., 7] = 0.6
    total, terms = world_model_loss(a, b, {"pos": 2.0, "rot": 1.0, "lin_vel": 0.5, "ang_vel": 1.0})
    torch.testing.assert_close(terms["pos"], torch.tensor(0.1))
    torch.testing.assert_close(terms["lin_vel"], torch.tensor(0.2))
    assert float(terms["rot"]) == 0.0 and float(terms["ang_vel"]) == 0.0
    torch.testing.assert_close(total, torch.tensor(0.3))
    # The rotation error ignores the quaternion's sign.
    c = a.clone()
    c[..., 3] = -1.0
    assert float(world_model_loss(a, c, {"pos": 1, "rot": 1, "lin_vel": 1, "ang_vel": 1})[1]["rot"]) == 0.0


def batch(walk_run, n=6, steps=4) -> WorldModelBatch:
    frames = np.arange(n)[:, None] + np.arange(steps + 1)
    kin = walk_run.state(np.zeros(frames.size, int), frames.ravel())
    states = torch.as_tensor(B.pack(kin)).reshape(n, steps + 1, 15, 13)
    return WorldModelBatch(states, torch.zeros(n, steps, 28))


def small(**kw) -> WorldModelLearner:
    return WorldModelLearner(15, 28, 1 / 30, WorldModelConfig(hidden=(32,), lr=1e-3, **kw))


def test_update_normalises_and_versions(walk_run):
    torch.manual_seed(0)
    learner = small()
    m = learner.update(batch(walk_run))
    assert learner.version == 1 and math.isfinite(m["loss"]) and m["grad_norm"] > 0
    assert float(learner.model.delta_norm.count) == 6 * 4 * 15 / 15  # one row of deltas per transition
    assert {"pos", "rot", "lin_vel", "ang_vel", "lr", "skipped_updates"} <= m.keys()


def test_non_finite_loss_skips_and_weights_stay_finite(walk_run):
    torch.manual_seed(0)
    learner = small()
    learner.update(batch(walk_run))
    published = learner.get_weights()
    bad = batch(walk_run)
    bad.actions[0, 0, 0] = float("inf")
    before = {k: v.clone() for k, v in learner.model.state_dict().items()}
    m = learner.update(bad)
    assert m["skipped_updates"] == 1 and learner.version == 1
    # Nothing moved, and the normalisers ignored the corrupt row.
    for k, v in learner.model.state_dict().items():
        assert torch.isfinite(v).all(), k
    for k, v in learner.model.net.state_dict().items():
        torch.testing.assert_close(v, before["net." + k])
    # Corrupt the parameters directly: get_weights returns the last good snapshot.
    with torch.no_grad():
        next(learner.model.net.parameters()).fill_(float("nan"))
    learner.version += 1
    assert learner.get_weights() is published
    fresh = small()
    with torch.no_grad():
        next(fresh.model.net.parameters()).fill_(float("nan"))
    with pytest.raises(NonFiniteWeightsError):
        fresh.get_weights()


def test_set_weights_copies_version_and_values(walk_run):
    torch.manual_seed(0)
    a, b = small(), small()
    a.update(batch(walk_run))
    b.set_weights(a.get_weights())
    assert b.version == 1
    x = batch(walk_run)
    torch.testing.assert_close(a.predict(x.states[:, 0], x.actions), b.predict(x.states[:, 0], x.actions))


def test_schedules():
    assert Schedule(0.5)(10_000) == 0.5
    assert Schedule(0.0, 1.0, "linear", steps=10)(5) == 0.5
    stairs = Schedule(0.01, 0.1, "staircase", steps=40_000, every=4_000)
    assert stairs(3_999) == 0.01 and stairs(4_000) == pytest.approx(0.019) and stairs(10**6) == pytest.approx(0.1)
    decay = Schedule(0.01, 1e-3, "exp", every=50, factor=0.7)
    assert decay(49) == 0.01 and decay(50) == pytest.approx(0.007) and decay(10**5) == 1e-3
    with pytest.raises(ValueError, match="unknown schedule kind"):
        Schedule(1.0, kind="cosine")


def test_build_world_model_is_the_learners_network():
    config = WorldModelConfig(hidden=(16, 8), activation="relu", integrator="midpoint")
    torch.manual_seed(0)
    learner = WorldModelLearner(15, 28, 1 / 20, config)
    torch.manual_seed(0)
    model = build_world_model(15, 28, config, 1 / 20)
    assert (model.dt, model.integrator) == (learner.model.dt, learner.model.integrator) == (1 / 20, "midpoint")
    mine, theirs = model.state_dict(), learner.model.state_dict()
    assert mine.keys() == theirs.keys()
    for k in mine:
        torch.testing.assert_close(mine[k], theirs[k])  # same layers, same initialisation under one seed


def test_physicsvaes_regress_layer_learns_the_next_features_by_mse(walk_run):
    """kind=regress: Table 2's plain MLP from (s, a) to s′, trained by the mean squared error over every
    element (regression_loss, worked by hand), learns one batch of walk transitions (the error falls by
    more than half in 300 steps); rollouts longer than one step and unknown kinds are refused."""
    from workers.losses.world_model import regression_loss
    from workers.models.world_model import StateRegressor

    loss, terms = regression_loss(torch.tensor([[1.0, 2.0], [0.0, 0.0]]), torch.tensor([[0.0, 0.0], [0.0, 2.0]]))
    assert float(loss) == pytest.approx((1 + 4 + 0 + 4) / 4) and terms["mse"] is loss
    torch.manual_seed(0)
    learner = WorldModelLearner(15, 28, 1 / 30, WorldModelConfig(kind="regress", hidden=(64, 64), activation="relu",
                                                                  rollout_steps=1, lr=1e-3))  # fmt: skip
    assert isinstance(learner.model, StateRegressor)
    b = batch(walk_run, steps=1)
    first = learner.update(b)["mse"]
    for _ in range(300):
        last = learner.update(b)["mse"]
    assert last < 0.5 * first
    with torch.no_grad():
        predicted = learner.model.next_features(b.states[:, :-1], b.actions)
        want = ((predicted - B.features(b.states[:, 1:])) ** 2).mean()
        torch.testing.assert_close(learner.loss(b)[1]["mse"], want)
    with pytest.raises(ValueError, match="world_model.rollout_steps: a regress layer"):
        WorldModelConfig(kind="regress", rollout_steps=8)
    with pytest.raises(ValueError, match="world_model.kind: unknown"):
        WorldModelConfig(kind="lstm")


def test_a_step_given_the_features_is_the_step_that_computes_them(walk_run):
    """A rollout hands each state's features to the model (computed once for the policy and the model); the
    prediction is the one the model makes from the body state alone."""
    torch.manual_seed(0)
    model = WorldModel(15, 28, (32, 32))
    bs = torch.as_tensor(B.pack(walk_run.state(np.array([0, 1]), np.array([5, 40]))))
    action = 0.3 * torch.randn(2, 28)
    model.observe(bs, action, bs)
    assert torch.equal(model(bs, action, B.features(bs)), model(bs, action))
