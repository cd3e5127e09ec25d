"""The world model learns our humanoid's dynamics well enough to beat constant-velocity extrapolation."""

from __future__ import annotations

import torch

from workers.models.body_state import LIN, POS


def test_world_model_predicts_8_steps_open_loop(world_model_run, held_out):
    learner, history = world_model_run
    assert history[-1]["loss"] < 0.5 * history[0]["loss"]
    starts = held_out.windows(8)
    batch = held_out.batch(starts, 8)
    true = batch.states[:, 1:, :, POS]
    predicted = learner.predict(batch.states[:, 0], batch.actions)[..., POS]
    steps = torch.arange(1, 9, dtype=true.dtype).view(1, 8, 1, 1) / 30
    constant_velocity = batch.states[:, :1, :, POS] + steps * batch.states[:, :1, :, LIN]
    # Mean body-position error (m) over windows and bodies, at each of the 8 steps.
    model_error = (predicted - true).norm(dim=-1).mean(dim=(0, 2))
    baseline_error = (constant_velocity - true).norm(dim=-1).mean(dim=(0, 2))
    print("world model", model_error.numpy().round(3), "constant velocity", baseline_error.numpy().round(3))
    assert len(starts) > 300
    assert model_error[-1] <= 0.5 * baseline_error[-1]
    assert model_error.mean() <= 0.5 * baseline_error.mean()
