"""SimConfig.backend: "mujoco" (the default) or "warp", refused in one line where the warp extra is missing;
make_sim builds the backend a config names, BatchedSim runs MuJoCo C only (WarpSim: test_warp_sim.py)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from workers.sim.env import BatchedSim, SimConfig, make_sim
from workers.sim.warp_physics import WarpUnavailable


def test_default_backend_is_mujoco():
    assert SimConfig().backend == "mujoco"


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="'bullet'"):
        SimConfig(backend="bullet")


def test_warp_without_the_extra_is_refused_in_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco_warp", None)  # as if not installed
    with pytest.raises(WarpUnavailable) as e:
        SimConfig(backend="warp")
    message = str(e.value)
    assert "pip install -e '.[warp]'" in message and "\n" not in message


def test_batched_sim_refuses_a_warp_config(character, walk_run):
    pytest.importorskip("mujoco_warp")
    with pytest.raises(ValueError, match="BatchedSim runs sim backend 'mujoco', the config says 'warp'.*make_sim"):
        BatchedSim(character, walk_run, 2, SimConfig(backend="warp"))


def test_make_sim_builds_batched_sim_without_the_warp_extra(character, walk_run, monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco_warp", None)
    monkeypatch.setitem(sys.modules, "warp", None)
    sim = make_sim(character, walk_run, 2, seed=3)
    assert type(sim) is BatchedSim and sim.config == SimConfig() and sim.num_envs == 2
    assert type(make_sim(character, walk_run, 1, SimConfig(sim_hz=120.0))) is BatchedSim


def test_mujoco_c_steps_a_tensor_of_actions_as_their_numpy(character, walk_run):
    """`Simulator.step` takes a tensor as well as NumPy; MuJoCo C copies it to the host: the same bits."""
    import torch

    sims = [make_sim(character, walk_run, 3, seed=1) for _ in range(2)]
    actions = character.qpos_to_action(sims[0].kin_state().qpos).astype(np.float32) + 0.1
    results = [sims[0].step(actions), sims[1].step(torch.from_numpy(actions))]
    np.testing.assert_array_equal(results[1].kin.qpos, results[0].kin.qpos)
    with pytest.raises(ValueError, match=r"actions must be \[3, 28\], got \[2, 28\]"):
        sims[1].step(torch.zeros(2, 28))
