"""The VAE controller (controlvae objective) learns to reconstruct walk and run through a frozen world model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.learners.base import Schedule
from workers.learners.vae import VAEBatch, VAELearner, vae_config
from workers.models.body_state import reference_windows


@pytest.mark.parametrize("prior", ["conditional", "standard_normal", "learned"])
def test_vae_halves_its_reconstruction_loss(prior, vae_runs):
    _, history = vae_runs(prior)
    rec = np.array([h["rec"] for h in history])
    first, last = rec[0], rec[-20:].mean()
    print(f"{prior}: rec {first:.2f} -> {last:.2f}, kl {history[-1]['kl']:.2f}")
    assert np.isfinite(rec).all()
    assert last <= 0.5 * first


@pytest.mark.parametrize("objective", ["physicsvae", "pulse"])
def test_behaviour_cloning_objectives_learn_the_expert(objective, walk_run, trajectories, world_model):
    """PhysicsVAE (BC + α·simulation consistency, α = 1e-4) and PULSE (distillation + L_regu) on the
    noisy-tracking trajectories, whose actions stand in for the expert's or teacher's."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    steps = 4
    config = vae_config(
        objective=objective,
        prior="standard_normal" if objective == "physicsvae" else "learned",
        latent_dim=16,
        encoder_hidden=(128, 128),
        policy="mlp",
        policy_hidden=(256, 256),
        lr=1e-3,
        optimizer="adam",
        beta=Schedule(0.01),
    )
    learner = VAELearner(15, 28, config, world_model=world_model.model, seed=0)
    starts = trajectories.windows(steps)
    key = "bc" if objective == "physicsvae" else "distill"
    history = []
    for _ in range(150):
        pick = starts[rng.integers(len(starts), size=64)]
        window = trajectories.batch(pick, steps)
        clip, frame = trajectories.clip_id[pick[:, 0], pick[:, 1]], trajectories.frame[pick[:, 0], pick[:, 1]]
        reference = reference_windows(walk_run, clip, frame, steps)
        history.append(learner.update(VAEBatch(window.states, torch.as_tensor(reference), window.actions)))
    losses = np.array([h[key] for h in history])
    print(f"{objective}: {key} {losses[0]:.2f} -> {losses[-20:].mean():.2f}")
    assert np.isfinite(losses).all()
    assert losses[-20:].mean() <= 0.5 * losses[0]
