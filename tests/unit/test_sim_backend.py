"""SimConfig.backend: "mujoco" (the default) or "warp", refused in one line where the warp extra is missing;
make_sim builds the backend a config names, BatchedSim runs MuJoCo C only (WarpSim: test_warp_sim.py)."""

from __future__ import annotations

import sys

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
