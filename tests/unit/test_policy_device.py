"""Where a rollout policy's inference runs (`Policy.to`): its networks, the ones it makes later, and its noise.

This machine has no GPU, so the placement is checked on PyTorch's `meta` device (parameters without
storage, which still report where they are), and the actions' equality across devices only where
CUDA is present (the GPU machine's run of scripts/device-warp.sh; skipped here).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from workers.body.features import StateLayout
from workers.learners.base import Weights
from workers.learners.ppo import PPOConfig, build_actor_critic
from workers.learners.task import TaskConfig
from workers.learners.vae import VAEConfig, build_controller
from workers.models import body_state
from workers.models.device_features import DeviceReference
from workers.models.nets import gaussian
from workers.policies import ExpertPolicy, GaussianPolicy, VAEPolicy
from workers.sim.env import make_sim
from workers.task.policy import TaskPPOPolicy, TaskRolloutPolicy

SKILL = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(32,))
PPO = PPOConfig(policy_hidden=(16,), value_hidden=(16,))
M = 4


def test_gaussian_draws_the_generators_numbers_wherever_it_puts_them():
    reference = torch.Generator().manual_seed(5)
    first = torch.randn((3, 4), generator=reference)
    torch.randn(7, generator=reference)
    gen = torch.Generator().manual_seed(5)
    np.testing.assert_array_equal(gaussian((3, 4), gen).numpy(), first.numpy())  # exactly torch.randn's
    moved = gaussian((7,), gen, device="meta")
    assert moved.device.type == "meta" and moved.shape == (7,)
    # The draw advanced the CPU stream as one of 7 numbers does: the next draw is the eighth onward.
    np.testing.assert_array_equal(gaussian((2,), gen).numpy(), torch.randn(2, generator=reference).numpy())


def _ppo_expert(character) -> Weights:
    module = build_actor_critic(2 * StateLayout(character.num_bodies).dim, character.num_actions, PPO)
    payload = {"kind": "ppo", "config": PPO, "observation": "imitation", "residual": True}
    return Weights(1, {**payload, "module": module.state_dict()})


def _vae_expert(character) -> Weights:
    controller = build_controller(character.num_bodies, character.num_actions, SKILL)
    return Weights(2, {"kind": "vae", "config": SKILL, "module": controller.state_dict()})


def _skill(character) -> dict:
    controller = build_controller(character.num_bodies, character.num_actions, SKILL)
    return {"skill": {"config": SKILL, "module": controller.state_dict(), "prior_action": True}}


def _policies(character):
    """(name, policy, how to give it its weights) for every kind of rollout policy."""
    b, a = character.num_bodies, character.num_actions
    s_dim = StateLayout(b).dim
    gaussian_module = build_actor_critic(2 * s_dim, a, PPO)
    task = TaskConfig(task="point_goal", sigma=0.5, hidden=(16,), helper_hidden=(16,))
    task_ppo = TaskConfig(task="point_goal", trainer="ppo", reward="progress", sigma=0.5)
    return [
        ("vae", VAEPolicy(b, a, SKILL), lambda p: None),
        ("gaussian", GaussianPolicy(gaussian_module, "imitation", residual=True), lambda p: None),
        ("expert-ppo", ExpertPolicy(b, a), lambda p: p.set_weights(_ppo_expert(character))),
        ("expert-vae", ExpertPolicy(b, a), lambda p: p.set_weights(_vae_expert(character))),
        ("task", TaskRolloutPolicy(b, a, task, 30.0), lambda p: p.configure(_skill(character))),
        ("task-ppo", TaskPPOPolicy(b, a, task_ppo, 30.0, PPO), lambda p: p.configure(_skill(character))),
    ]


def _parameters(policy) -> list[torch.Tensor]:
    nets = list(policy.networks())
    inner = getattr(policy, "inner", None)
    if inner is not None:
        nets += inner.networks()
    return [t for net in nets for t in list(net.parameters()) + list(net.buffers())]


@pytest.mark.parametrize("moved_first", [True, False], ids=["to-then-weights", "weights-then-to"])
def test_every_policy_runs_its_networks_on_its_device_including_those_it_makes_later(character, moved_first):
    for name, policy, give_weights in _policies(character):
        if moved_first:
            policy.to("meta")
            give_weights(policy)
        else:
            give_weights(policy)
            policy.to("meta")
        tensors = _parameters(policy)
        assert tensors, name
        assert policy.device == torch.device("meta"), name
        assert {t.device.type for t in tensors} == {"meta"}, name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU on this machine (the GPU machine runs it)")
def test_every_policy_acts_the_same_on_the_gpu_as_on_the_cpu(character, walk_run):
    """From the same random streams and states, the actions and extras agree to float32 rounding."""
    sim = make_sim(character, walk_run, M, seed=0)
    bs = body_state.pack(sim.kin_state())
    for name, policy, give_weights in _policies(character):
        torch.manual_seed(0)
        give_weights(policy)
        results = []
        for device in ("cpu", "cuda"):
            p = copy.deepcopy(policy).to(device)
            p.bind(M, np.random.default_rng(1), torch.Generator().manual_seed(2))
            results.append(p.act(sim, bs))
        (a_cpu, x_cpu), (a_gpu, x_gpu) = results
        np.testing.assert_allclose(a_gpu, a_cpu, atol=1e-4, err_msg=name)
        for key, value in x_cpu.items():
            np.testing.assert_allclose(x_gpu[key], value, atol=1e-4, err_msg=f"{name}: {key}")


@pytest.mark.parametrize("kind", ["state", "imitation", "mimic"])
def test_an_observation_made_on_the_device_is_the_numpy_one(character, walk_run, kind):
    """`observe_on` (torch, float32, where the policy runs) gives `observe`'s numbers (NumPy) to float rounding."""
    from workers.policies import observe, observe_on

    sim = make_sim(character, walk_run, M, seed=0)
    sim.step(character.qpos_to_action(sim.kin_state().qpos))  # moving bodies, some frames on
    bs = sim.body_states()
    want = observe(kind, sim, bs)
    got = observe_on(torch.device("cpu"), kind, sim, bs)
    assert got.dtype == torch.float32 and got.shape == want.shape
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-5)
    assert observe_on(torch.device("meta"), kind, sim, bs).device.type == "meta"  # made where it is asked


def test_a_gaussian_policy_beside_a_simulator_on_its_device_observes_there(character, walk_run, monkeypatch):
    """Beside a simulator that computes on its device, the policy's observation is `observe_on`'s, recorded as
    the extras' `obs`; beside MuJoCo C it is NumPy's, bit for bit as before."""
    from workers.policies import observe, observe_on

    sim = make_sim(character, walk_run, M, seed=0)
    bs = sim.body_states()
    module = build_actor_critic(2 * StateLayout(character.num_bodies).dim, character.num_actions, PPO)
    policy = GaussianPolicy(module, "imitation", residual=True)
    policy.bind(M, np.random.default_rng(1), torch.Generator().manual_seed(2))
    host_actions, extras = policy.act(sim, bs)
    assert isinstance(host_actions, np.ndarray)
    np.testing.assert_array_equal(extras["obs"], observe("imitation", sim, bs))
    monkeypatch.setattr(type(sim), "computes_on_device", True)  # and its library's frames "on the device":
    reference = DeviceReference(walk_run, "cpu")
    monkeypatch.setattr(type(sim), "device_reference", lambda self: reference)
    calls = []
    monkeypatch.setattr("workers.policies.observe_on", lambda *a: calls.append(a[0]) or observe_on(*a))
    policy.bind(M, np.random.default_rng(1), torch.Generator().manual_seed(2))
    actions, extras = policy.act(sim, bs)
    assert all(isinstance(v, torch.Tensor) for v in (actions, *extras.values()))  # kept on the device
    # the same draws; the residual's offset looked up on the device
    np.testing.assert_allclose(actions.numpy(), host_actions, rtol=0, atol=1e-4)
    np.testing.assert_array_equal(policy.observe(sim, bs), extras["obs"])
    assert calls == [torch.device("cpu")] * 2
    np.testing.assert_allclose(extras["obs"], observe("imitation", sim, bs), rtol=0, atol=1e-5)
