"""The RLlib side of the peer benchmark: RLlib's PPO trains on our batched humanoid (optional extra `peer`)."""

from __future__ import annotations

import math
import sys

import pytest

from orchestrator.bench import peer_rllib


def test_missing_rllib_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray.rllib.algorithms.ppo", None)  # makes the import fail
    with pytest.raises(ImportError, match=r"pip install -e \.\[peer\]"):
        peer_rllib.measure_rllib(2, (32,), 64, 32, iterations=1, warmup=1, seed=0)


@pytest.mark.slow
@pytest.mark.ray
def test_measure_rllib_tiny():
    pytest.importorskip("ray.rllib")
    r = peer_rllib.measure_rllib(
        num_envs=2, hidden=(32, 32), train_batch_size=64, minibatch_size=32, iterations=1, warmup=1, seed=0
    )
    assert r["env_runners"] == 0 and r["num_envs"] == 2 and r["hidden"] == [32, 32]
    assert r["train_env_steps"] >= 64 and r["sample_env_steps"] >= 64
    for k in ("train_steps_per_s", "sample_steps_per_s"):
        assert math.isfinite(r[k]) and r[k] > 0


@pytest.mark.slow
@pytest.mark.ray
def test_peer_counts_only_the_steps_each_side_trained_on():
    # RLlib reports the steps of the sampling-only calls at its next train(); counted there, they
    # made its end-to-end figure 1.5x too high. Each block must hold per_round batches, no more.
    pytest.importorskip("ray.rllib")
    from orchestrator.bench import peer

    batch, envs, per_round = 64, 2, 1
    r = peer.run(envs, (32, 32), batch, 32, rounds=3, warmup=1, seed=0, runtime="local", per_round=per_round)
    for ours, theirs in r["end_to_end"]["steps_per_round"]:
        assert ours == per_round * batch
        assert per_round * batch <= theirs < per_round * (batch + 2 * envs)
