"""Device mixing caught on a CPU, under a stand-in GPU.

The stand-in (`standin_gpu.py`, beside this file): tensors with real values that say they are on another device
and refuse to mix with CPU tensors (or a generator of the other device) as CUDA does. Under it, each computing the
same numbers as on the CPU:
- every learner's update and state dict;
- every rollout policy acting beside MuJoCo C, alone and in a rollout worker's loop with every recorder;
- the tracking action with a real controller on either side of a goal on the GPU;
- every evaluation protocol of a VAE controller and the recordings its videos render, beside MuJoCo C, and (slow)
  the tracking ones beside MuJoCo Warp on its CPU device, which makes the goal there;
- a PPO policy's pose-error episodes and video episode, and a task policy's evaluation.

What it found, beyond issue 45's list: the time-until-fall, random-sampling and fall-video rollouts drew z with a
CPU generator beside the controller's device and read its action with `.numpy()` (fixed:
`workers.evaluation.controller.prior_action`). Rendering itself
(qpos to pixels, in a child process) and the model's export hold no tensor of a device.

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
        with pytest.raises(RuntimeError, match="generator on the cpu"):
            torch.randn(3, generator=torch.Generator().manual_seed(0), device=DEVICE)
        assert torch.randn(3, generator=torch.Generator(device=DEVICE), device=DEVICE).device == DEVICE


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
    """The worker's own loop around the policy (observations, actions into MuJoCo C, the trajectory's arrays, the
    recorders' extras) with the policy on the GPU: no tensor crosses unmoved, and the trajectory is the CPU's."""
    from workers.body.features import StateLayout
    from workers.recorders import AMPFeatures, ImitationReward, TrackingReward
    from workers.rollout import RolloutWorker

    for name, policy, give_weights in _policies(character):
        trajectories = []
        for on_gpu in (False, True):
            with stand_in_gpu() if on_gpu else contextlib.nullcontext():
                torch.manual_seed(0)
                give_weights(policy)
                weights = np.ones(StateLayout(character.num_bodies).dim)
                recorders = [AMPFeatures(character), ImitationReward(character), TrackingReward(weights)]
                policy.to(DEVICE if on_gpu else "cpu")
                worker = RolloutWorker(character, walk_run, 3, policy, seed=4, recorders=recorders)
                trajectories.append(worker.collect(6))
        cpu, gpu = trajectories
        for key in ("states", "next_states", "actions", "done", "clip_id", "frame"):
            np.testing.assert_allclose(
                getattr(gpu, key), getattr(cpu, key), rtol=1e-5, atol=1e-6, err_msg=f"{name}: {key}"
            )
        assert cpu.extras.keys() == gpu.extras.keys() and len(cpu.extras) >= 3, name
        for key, value in cpu.extras.items():
            np.testing.assert_allclose(gpu.extras[key], value, rtol=1e-5, atol=1e-6, err_msg=f"{name}: {key}")


def _controller(character):
    from workers.learners.vae import VAEConfig, build_controller

    torch.manual_seed(0)
    config = VAEConfig(latent_dim=4, encoder_hidden=(16,), policy_hidden=(16,))
    return build_controller(character.num_bodies, character.num_actions, config)


def _evaluations():
    """(name, run(controller, character, library, sim config) -> what it measures or records, as arrays): every
    evaluation protocol and recording that drives a VAE controller, small."""
    from workers.evaluation import controller as protocols
    from workers.evaluation.render import record_fall_rollouts, record_tracking
    from workers.evaluation.success import tracking_success

    def success(c, ch, lib, sc):  # with PULSE's student, as `orchestrator.algos.pulse` runs it (without gradients)
        with torch.no_grad():
            return tracking_success(lambda sim, bs: protocols.posterior_mean_action(c, sim, bs), ch, lib, 0.2, sc)

    return [
        ("time_until_fall", lambda c, ch, lib, sc: protocols.time_until_fall(c, ch, lib, 3, 0.4, sim_config=sc)),
        ("tracking_error", lambda c, ch, lib, sc: protocols.tracking_error(c, ch, lib, 0.2, sim_config=sc)),
        ("random_sampling", lambda c, ch, lib, sc: protocols.random_sampling(c, ch, lib, 3, 0.2, sim_config=sc)),
        ("tracking_success", success),
        ("record_fall_rollouts", lambda c, ch, lib, sc: [r.qpos for r in record_fall_rollouts(c, ch, lib, 2, 0.3, sc)]),
        ("record_tracking", lambda c, ch, lib, sc: record_tracking(c, ch, lib, 0.2, sc).qpos),
    ]


def _arrays(result) -> list[np.ndarray]:
    if isinstance(result, dict):
        return [a for k in sorted(result) for a in _arrays(result[k])]
    if isinstance(result, list | tuple) and result and not isinstance(result[0], int | float):
        return [a for x in result for a in _arrays(x)]
    return [np.asarray(result, float)]


@pytest.mark.parametrize("index", range(6))
def test_every_evaluation_of_a_controller_on_the_gpu_beside_mujoco_c_measures_what_the_cpu_does(
    character, walk_run, index
):
    """The protocols (time until fall, tracking error, random sampling, PULSE's tracking success with the student)
    and the recordings the videos render, with the controller on the GPU and MuJoCo C on the CPU: z's noise from
    the same CPU stream, so the same numbers. Before `prior_action`, z was drawn with a CPU generator beside a
    controller on the GPU and its action read by `.numpy()`: refused."""
    name, run = _evaluations()[index]
    controller = _controller(character)
    want = _arrays(run(controller, character, walk_run, None))
    with stand_in_gpu():
        got = _arrays(run(controller.to(DEVICE), character, walk_run, None))
    assert len(got) == len(want) > 0, name
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6, err_msg=name)


def test_a_ppo_policys_evaluation_and_video_episode_on_the_gpu_as_on_the_cpu(character, walk_run):
    """AMP's pose error after DTW and its video's episode, and a task policy's evaluation, with the policies on
    the GPU beside MuJoCo C."""
    from workers.evaluation.imitation import pose_error_episodes
    from workers.evaluation.render import record_policy_episode
    from workers.evaluation.tasks import evaluate_task_policy

    policies = dict((name, (policy, give)) for name, policy, give in _policies(character))
    gaussian, _ = policies["gaussian"]
    task, configure = policies["task"]
    results = []
    for on_gpu in (False, True):
        with stand_in_gpu() if on_gpu else contextlib.nullcontext():
            torch.manual_seed(0)
            configure(task)
            gaussian.to(DEVICE if on_gpu else "cpu")
            task.to(DEVICE if on_gpu else "cpu")
            pose = pose_error_episodes(gaussian.mean_action, character, walk_run, 2, 0.2, seed=3)
            episode = record_policy_episode(gaussian.mean_action, character, walk_run, 0.2, seed=3)
            evaluated = evaluate_task_policy(task, character, walk_run, 2, 0.2, seed=3)
            results.append(_arrays([pose["curve"], episode.qpos, evaluated["curve"], evaluated["roots"]]))
    for g, w in zip(results[1], results[0], strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_the_tracking_evaluations_on_warps_cpu_device_with_the_controller_on_the_gpu(character, walk_run):
    """MuJoCo Warp on its CPU device makes the tracking goal there (a torch tensor, `Simulator.tracking_goal`); the
    controller on the GPU: the mirror of a CUDA simulator beside a CPU controller (the first bug of issue 45).
    Compiles MuJoCo Warp's kernels on a cold cache, hence `slow`."""
    pytest.importorskip("mujoco_warp")
    from workers.evaluation.controller import time_until_fall, tracking_error
    from workers.sim.env import SimConfig

    warp = SimConfig(backend="warp", device="cpu")
    controller = _controller(character)
    want = [tracking_error(controller, character, walk_run, 0.2, warp)["mean"],
            time_until_fall(controller, character, walk_run, 2, 0.2, sim_config=warp)["times"]]  # fmt: skip
    with stand_in_gpu():
        controller.to(DEVICE)
        got = [tracking_error(controller, character, walk_run, 0.2, warp)["mean"],
               time_until_fall(controller, character, walk_run, 2, 0.2, sim_config=warp)["times"]]  # fmt: skip
    np.testing.assert_allclose(np.hstack(got), np.hstack(want), rtol=1e-5, atol=1e-6)
