"""`bench host`: the rollout worker's control step with no physics, split into the policy's networks and the rest."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from orchestrator.bench import host
from orchestrator.bench.__main__ import main
from orchestrator.bench.sim import walk_run_setup


@pytest.fixture(scope="module")
def setup():
    return walk_run_setup(480.0, 30.0)


def test_the_frozen_simulator_leaves_the_bodies_where_they_are(setup):
    character, library = setup
    sim = host.FrozenSim(character, library, 3, seed=0)
    before = sim.kin_state()
    result = sim.step(np.zeros((3, character.num_actions)))
    np.testing.assert_array_equal(result.kin.xpos, before.xpos)
    np.testing.assert_array_equal(result.kin.qvel, before.qvel)
    assert not result.fell.any() and (sim.steps == 1).all()  # the reference moved on, the bodies did not


def test_the_networks_time_is_part_of_the_step_and_counted_once(setup):
    character, library = setup
    worker = host.frozen_worker("vae", character, library, 4, "cpu", seed=0)
    row = host.measure(worker, steps=4, collect=2)
    assert row["control_steps"] == 4 and row["envs"] == 4
    assert 0 < row["network_ms_per_step"] < row["ms_per_step"]
    assert row["host_ms_per_step"] == pytest.approx(row["ms_per_step"] - row["network_ms_per_step"])
    assert row["host_ceiling_control_steps_per_s"] > row["control_steps_per_s"]
    # The hooks are gone afterwards: the policy's submodules carry none.
    assert not any(m._forward_hooks or m._forward_pre_hooks for m in worker.policy.controller.modules())


def test_a_task_worker_records_its_reward_once(setup):
    """The task policy records its own reward (it is a recorder): the frozen worker keeps it once, so the reward
    of each step is written once, and the goals are drawn around the characters' roots."""
    character, library = setup
    worker = host.frozen_worker("task", character, library, 3, "cpu", seed=0)
    assert worker.recorders == [worker.policy]
    traj = worker.collect(2)
    distance = np.linalg.norm(traj.extras["goal"][0] - traj.states[0, :, 0, :2], axis=-1)
    assert ((distance >= 1.0 - 1e-5) & (distance <= 5.0 + 1e-5)).all()  # the point goal's 1-5 m
    assert traj.extras["reward"].shape == (2, 3) and np.isfinite(traj.extras["obs"]).all()


def test_nested_calls_are_timed_once(monkeypatch):
    ticks = iter(range(100))
    monkeypatch.setattr(host.time, "perf_counter", lambda: float(next(ticks)))  # each reading one second later
    outer = torch.nn.Sequential(torch.nn.Sequential(torch.nn.Identity()))
    clock = host.NetworkClock([outer, outer[0]], torch.device("cpu"))  # Identity runs inside outer[0]: both hooked
    outer(torch.zeros(1))
    assert clock.depth == 0 and clock.seconds == 1.0  # the outermost call's two readings, nothing nested


def test_modules_reached_below_the_networks_children_are_timed(monkeypatch):
    """A task policy's actor-critic keeps its MLPs in a ModuleDict and calls them from `act`: each is timed."""
    from workers.models.actor_critic import HelperActorCritic

    net = HelperActorCritic(5, 2, 3, 4, 0.1, policy_hidden=(8,), value_hidden=(8,), helper_hidden=(8,))
    ticks = iter(range(100))
    clock = host.NetworkClock([net], torch.device("cpu"))
    monkeypatch.setattr(host.time, "perf_counter", lambda: float(next(ticks)))
    net.act(torch.zeros(6, 5 + 2 + 3))
    assert clock.depth == 0 and clock.seconds == 3.0  # the normaliser, μ_g's MLP and the helper's: one second each


def test_the_table_names_every_policy_and_size(capsys):
    assert main(["host", "--policies", "tracker", "--envs", "2,3", "--steps", "2", "--collect", "1"]) == 0
    table = capsys.readouterr().out
    assert "policy on cpu" in table and table.count("tracker") == 2


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_a_gpu_that_is_not_there_is_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        main(["host", "--device", "cuda"])
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == "error: --device cuda: this machine has no CUDA GPU"


@pytest.mark.slow
def test_a_frozen_warp_worker_makes_its_state_on_the_device(setup, capsys):
    """`--sim warp`: the worker's simulator is MuJoCo Warp's, frozen (the controls are set, no physics step), and its
    step's state, features and rewards come from the device; the table has a row per engine."""
    pytest.importorskip("mujoco_warp")
    character, library = setup
    worker = host.frozen_worker("tracker", character, library, 3, "cpu", seed=0, sim="warp")
    assert worker.sim.computes_on_device
    before = worker.sim.body_states()
    traj = worker.collect(2)
    np.testing.assert_array_equal(traj.next_states[-1], before)  # nothing moved
    assert (traj.extras["reward"] > 0).all()
    assert (
        main(["host", "--policies", "tracker", "--envs", "2", "--steps", "2", "--collect", "1", "--sim", "mujoco,warp"])
        == 0
    )
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.startswith("tracker")]
    assert [r[1] for r in rows] == ["mujoco", "warp"]


def test_an_unknown_engine_is_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        main(["host", "--sim", "bullet"])
    assert e.value.code == 2 and "--sim: expected some of mujoco,warp, got bullet" in capsys.readouterr().err
