"""Device mixing caught on a CPU, under a stand-in GPU.

The stand-in (`standin_gpu.py`, beside this file): tensors with real values that say they are on another device
and refuse to mix with CPU tensors as CUDA does. Under it: every learner's update and state dict, the same numbers
as on the CPU; every rollout policy acting beside MuJoCo C, alone and in a rollout worker's loop; the tracking
action with a real controller on either side of a goal on the GPU.

Fake tensors (torch's FakeTensorMode) were tried first and cannot serve: they hold no values, so our normalisers'
first-batch branch (`count == 0`) and every learner's `.item()` refuse them, and a fake CUDA matrix product aborts the
process on a CPU-only build of torch (standin_gpu.py says more).
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
import torch
from standin_gpu import DEVICE, stand_in_gpu  # beside this file (pytest puts its folder on sys.path)
from test_learner_device import learners, step
from test_policy_device import _policies

from workers.evaluation.controller import posterior_mean

CUDA = torch.device("cuda", 0)
S, G, Z, A = 6, 5, 2, 3


def test_the_stand_in_gpu_refuses_a_mix_and_numpy_as_cuda_does():
    with stand_in_gpu():
        x = torch.ones(3).to(DEVICE)
        assert x.device == DEVICE and torch.equal((x * 2).cpu(), torch.full((3,), 2.0))
        with pytest.raises(RuntimeError, match="tensors on the GPU and on the cpu mixed"):
            x + torch.ones(3)
        assert float((x + torch.tensor(1.0)).sum()) == 6.0  # a 0-dimensional CPU tensor mixes, as on CUDA
        with pytest.raises(RuntimeError):
            x.numpy()


@pytest.mark.parametrize("index", range(7))
def test_every_learners_update_on_the_gpu_mixes_nothing_and_computes_what_the_cpu_does(walk_run, index):
    name, build, batch = learners(walk_run, "cpu")[index]
    torch.manual_seed(0)
    on_cpu = step(build(torch.device("cpu")), batch)
    with stand_in_gpu():
        torch.manual_seed(0)
        learner = build(DEVICE)
        assert all(p.device == DEVICE for p in learner.module.parameters()), name
        on_gpu = step(learner, batch)
        weights, state = learner.get_weights(), learner.state_dict()
    assert on_gpu == pytest.approx(on_cpu, rel=1e-6, abs=1e-9), name
    assert all(t.device.type == "cpu" for t in weights.state.values()), name
    assert all(t.device.type == "cpu" for t in state["module"].values()), name


def test_every_rollout_policy_acts_on_the_gpu_beside_mujoco_c_as_on_the_cpu(character, walk_run):
    from workers.models import body_state
    from workers.sim.env import make_sim

    sim = make_sim(character, walk_run, 4, seed=0)
    bs = body_state.pack(sim.kin_state())
    for name, policy, give_weights in _policies(character):
        torch.manual_seed(0)
        give_weights(policy)
        policy.bind(4, np.random.default_rng(1), torch.Generator().manual_seed(2))
        want, _ = policy.act(sim, bs)
        with stand_in_gpu():
            torch.manual_seed(0)
            give_weights(policy)
            policy.to(DEVICE).bind(4, np.random.default_rng(1), torch.Generator().manual_seed(2))
            got, _ = policy.act(sim, bs)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7, err_msg=name)


def test_the_drivers_evaluation_runs_warp_on_the_cpu_where_it_sees_no_gpu_and_the_workers_keep_theirs(monkeypatch):
    """Evaluation, videos and the model's export build their simulator in the driver, which holds no Ray GPU (a
    cluster's may have none): on a GPU it does not see, the same engine on Warp's CPU device; the rollout workers,
    which see theirs through Ray, keep `sim.device`. This machine has no GPU; torch's count stands in for one."""
    from orchestrator.compose import compose, validate
    from orchestrator.world import collection_sim_config, evaluation_sim_config

    cfg = validate(compose(["scale=smoke", "sim.backend=warp", "sim.device=cuda", "run_dir=unused"]))
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    assert evaluation_sim_config(cfg).device == "cpu" and evaluation_sim_config(cfg).backend == "warp"
    assert collection_sim_config(cfg).device == "cuda"
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert evaluation_sim_config(cfg).device == "cuda"


@pytest.mark.parametrize("controller_on", ["cpu", "gpu"])
def test_the_tracking_action_of_a_real_controller_wherever_it_and_the_goal_are(controller_on):
    """Our VAE controller (its normalisers included), on either side of a goal made on the GPU: the action comes
    back from the controller's device; the old concatenation of the two as they came is refused."""
    from workers.learners.vae import VAEConfig, build_controller

    config = VAEConfig(latent_dim=4, encoder_hidden=(16,), policy_hidden=(16,))
    controller = build_controller(15, 28, config)
    s = torch.zeros(3, controller.state_norm.mean.shape[0])
    with stand_in_gpu():
        if controller_on == "gpu":
            controller.to(DEVICE)
            goal = torch.full_like(s, 0.1)  # the state and the goal on the CPU
        else:
            goal = torch.full_like(s, 0.1).to(DEVICE)  # the goal on the GPU, as beside MuJoCo Warp on CUDA
        with pytest.raises(RuntimeError, match="mixed"):
            controller.encode(s, goal)
        action = posterior_mean(controller, s, goal).cpu()
    assert action.shape == (3, 28) and torch.isfinite(action).all()


def test_a_rollout_worker_collects_with_each_policy_on_the_gpu_as_on_the_cpu(character, walk_run):
    """The worker's own loop around the policy (observations, actions into MuJoCo C, the trajectory's arrays)
    with the policy on the GPU: no tensor crosses unmoved, and the trajectory is the CPU's."""
    from workers.rollout import RolloutWorker

    for name, policy, give_weights in _policies(character):
        trajectories = []
        for on_gpu in (False, True):
            with stand_in_gpu() if on_gpu else contextlib.nullcontext():
                torch.manual_seed(0)
                give_weights(policy)
                worker = RolloutWorker(character, walk_run, 3, policy.to(DEVICE if on_gpu else "cpu"), seed=4)
                trajectories.append(worker.collect(6))
        cpu, gpu = trajectories
        for key in ("states", "next_states", "actions", "done", "clip_id", "frame"):
            np.testing.assert_allclose(
                getattr(gpu, key), getattr(cpu, key), rtol=1e-5, atol=1e-6, err_msg=f"{name}: {key}"
            )
