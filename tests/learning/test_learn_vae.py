"""The VAE controller (controlvae objective) learns to reconstruct walk and run through a frozen world model."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("prior", ["conditional", "standard_normal", "learned"])
def test_vae_halves_its_reconstruction_loss(prior, vae_runs):
    _, history = vae_runs(prior)
    rec = np.array([h["rec"] for h in history])
    first, last = rec[0], rec[-20:].mean()
    print(f"{prior}: rec {first:.2f} -> {last:.2f}, kl {history[-1]['kl']:.2f}")
    assert np.isfinite(rec).all()
    assert last <= 0.5 * first
