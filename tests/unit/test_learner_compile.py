"""`Learner.compile`: a compiled loss gives the eager loss and gradients on a fixed batch, and the same
parameters after updates; a loss that takes a gradient of a gradient is refused in one line; the batch
reaches the compiled loss already on the device."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.learners.base import Weights
from workers.learners.discriminator import DiscriminatorBatch, DiscriminatorLearner
from workers.learners.vae import ControlVAEObjective, VAEBatch, VAELearner, vae_config
from workers.learners.world_model import WorldModelBatch, WorldModelConfig, WorldModelLearner
from workers.models.nets import Normalizer
from workers.models.world_model import WorldModel

NUM_BODIES, ACTION_DIM, DT = 15, 28, 1.0 / 30.0


def _batch(n: int = 8, t: int = 3) -> WorldModelBatch:
    gen = torch.Generator().manual_seed(1)
    pos = torch.randn(n, t + 1, NUM_BODIES, 3, generator=gen) * 0.3 + torch.tensor([0.0, 0.0, 1.0])
    quat = torch.randn(n, t + 1, NUM_BODIES, 4, generator=gen)
    quat = quat / quat.norm(dim=-1, keepdim=True)
    vel = torch.randn(n, t + 1, NUM_BODIES, 6, generator=gen) * 0.5
    return WorldModelBatch(torch.cat((pos, quat, vel), -1), torch.randn(n, t, ACTION_DIM, generator=gen) * 0.3)


def _vae_learner() -> VAELearner:
    """A tiny ControlVAE learner, the same from the same seed."""
    torch.manual_seed(0)
    config = ControlVAEObjective(
        latent_dim=4, encoder_hidden=(16,), num_experts=2, policy_hidden=(16,), gate_hidden=(8,)
    )
    return VAELearner(NUM_BODIES, ACTION_DIM, config, world_model=WorldModel(NUM_BODIES, ACTION_DIM, (16,)))


def _learner() -> WorldModelLearner:
    torch.manual_seed(0)
    return WorldModelLearner(NUM_BODIES, ACTION_DIM, DT, WorldModelConfig(hidden=(32, 32), rollout_steps=3))


@pytest.mark.slow  # torch.compile's first call builds C++ kernels: tens of seconds on this machine
def test_compiled_world_model_matches_eager() -> None:
    batch = _batch()
    eager, compiled = _learner(), _learner()
    compiled.compile()
    for learner in (eager, compiled):
        learner.before_update(batch)

    losses, grads = [], []
    for learner in (eager, compiled):
        total, terms = learner.loss(batch)
        learner.optimizer.zero_grad(set_to_none=True)
        total.backward()
        losses.append((float(total), {k: float(v) for k, v in terms.items()}))
        grads.append([p.grad.clone() for p in learner.parameters()])
    assert losses[1][0] == pytest.approx(losses[0][0], rel=1e-5)
    assert losses[1][1] == pytest.approx(losses[0][1], rel=1e-5)
    for g_eager, g_compiled in zip(*grads, strict=True):
        torch.testing.assert_close(g_compiled, g_eager, rtol=1e-4, atol=1e-6)

    for learner in (eager, compiled):
        for _ in range(2):
            metrics = learner.update(batch)
            assert "grad_norm" in metrics  # a step was taken, not skipped
    for p_eager, p_compiled in zip(eager.parameters(), compiled.parameters(), strict=True):
        torch.testing.assert_close(p_compiled, p_eager, rtol=1e-4, atol=1e-6)
    assert compiled.version == eager.version == 2
    assert compiled.state_dict()["module"].keys() == eager.state_dict()["module"].keys()


def test_discriminator_refuses_compile() -> None:
    learner = DiscriminatorLearner(105)
    with pytest.raises(ValueError, match="disc: its loss takes a gradient of a gradient"):
        learner.compile()


def test_on_device_converts_the_float_arrays_only() -> None:
    """What a compiled loss is given: float arrays as float32 tensors on the device, the rest untouched."""
    learner = DiscriminatorLearner(4)
    data = np.arange(8.0).reshape(2, 4)  # float64
    skills = np.array([0, 1])
    batch = learner.on_device(DiscriminatorBatch(data, torch.ones(3, 4, dtype=torch.float64), skills, None))
    assert batch.data_obs.dtype == torch.float32 and batch.data_obs.device == learner.device
    torch.testing.assert_close(batch.data_obs, torch.arange(8.0).reshape(2, 4))
    assert batch.policy_obs.dtype == torch.float32
    assert batch.data_skill is skills and batch.policy_skill is None
    assert learner.on_device(data) is data  # not a dataclass: as it is


@pytest.mark.slow  # compiles
def test_compiled_normalizer_matches_eager_before_and_after_samples() -> None:
    """In a graph the normaliser skips its cache and its branch: identity before any sample, (x - mean) / std
    after, as in eager."""
    norm = Normalizer(3)
    compiled = torch.compile(norm, dynamic=False)
    x = torch.tensor([[1.0, -2.0, 3.0], [0.5, 0.0, -1.0]])
    torch.testing.assert_close(compiled(x), x)  # no sample yet
    norm.update(torch.tensor([[0.0, 1.0, 2.0], [2.0, 5.0, 2.0]]))  # mean (1, 3, 2), std (1, 2, eps)
    expected = (x - torch.tensor([1.0, 3.0, 2.0])) / torch.tensor([1.0, 2.0, 1e-2])
    torch.testing.assert_close(norm(x), expected)
    torch.testing.assert_close(compiled(x), expected)


@pytest.mark.slow  # compiles
def test_compiled_controlvae_matches_eager_with_the_same_draws() -> None:
    """The VAE's loss draws latent samples and action noise; compiled, it is given them drawn ahead from the
    same generator, so its loss and gradients match eager's from the same generator state."""
    states = _batch(n=8, t=3).states
    batch = VAEBatch(states, states.clone())

    eager, compiled = _vae_learner(), _vae_learner()
    compiled.compile()
    results = []
    for vae in (eager, compiled):
        vae.before_update(batch)
        total, terms = vae.loss(batch)
        vae.optimizer.zero_grad(set_to_none=True)
        total.backward()
        results.append((float(total), float(terms["kl"]), [p.grad.clone() for p in vae.parameters()]))
    assert results[1][0] == pytest.approx(results[0][0], rel=1e-5)
    assert results[1][1] == pytest.approx(results[0][1], rel=1e-5)
    for g_eager, g_compiled in zip(results[0][2], results[1][2], strict=True):
        torch.testing.assert_close(g_compiled, g_eager, rtol=1e-4, atol=1e-6)


@pytest.mark.slow  # compiles
def test_compiled_controlvae_follows_new_batches_and_world_model_weights() -> None:
    """As in the loop: each update on a new batch (the state normaliser's statistics move) and new world-model
    weights loaded between updates. A compiled graph that had kept any of them as constants from its first
    call would drift from eager here, where the fixed-batch test above cannot tell."""
    eager, compiled = _vae_learner(), _vae_learner()
    compiled.compile()
    gen = torch.Generator().manual_seed(5)
    for k in range(3):
        if k:
            torch.manual_seed(10 + k)
            weights = Weights(k, WorldModel(NUM_BODIES, ACTION_DIM, (16,)).state_dict())
            for vae in (eager, compiled):
                vae.set_world_model_weights(weights)
        states = _batch(n=8, t=3).states * (1 + k) + torch.randn(1, generator=gen)
        batch = VAEBatch(states, states.flip(0))
        losses = [vae.update(batch)["loss"] for vae in (eager, compiled)]
        assert losses[1] == pytest.approx(losses[0], rel=1e-5)
    assert compiled.world_model.state_dict()["net.0.weight"].equal(weights.state["net.0.weight"])
    for p_eager, p_compiled in zip(eager.parameters(), compiled.parameters(), strict=True):
        torch.testing.assert_close(p_compiled, p_eager, rtol=1e-4, atol=1e-6)


def test_runtime_learner_compile_compiles_every_learner_but_the_discriminator() -> None:
    from types import SimpleNamespace

    from orchestrator.components.base import compiled

    def cfg(mode: str) -> SimpleNamespace:
        return SimpleNamespace(runtime=SimpleNamespace(learner_compile=mode))

    eager = compiled(_learner(), cfg("eager"))
    assert eager.loss.__func__ is WorldModelLearner.loss  # the bound method, untouched
    world_model = compiled(_learner(), cfg("default"))
    assert getattr(world_model.loss, "__func__", None) is not WorldModelLearner.loss  # through torch.compile
    disc = compiled(DiscriminatorLearner(105), cfg("reduce-overhead"))  # refuses compile(); stays eager here
    assert disc.loss.__func__ is DiscriminatorLearner.loss


@pytest.mark.slow  # compiles
@pytest.mark.parametrize(("objective", "prior"), [("physicsvae", "standard_normal"), ("pulse", "learned")])
def test_the_other_vae_objectives_compile_to_the_same_updates(objective: str, prior: str) -> None:
    states = _batch(n=8, t=3).states
    batch = VAEBatch(states, states.clone(), torch.randn(8, 3, ACTION_DIM, generator=torch.Generator().manual_seed(2)))
    losses = []
    for compile_it in (False, True):
        torch.manual_seed(0)
        config = vae_config(
            objective=objective, prior=prior, latent_dim=4, encoder_hidden=(16,), num_experts=2, policy_hidden=(16,)
        )
        vae = VAELearner(NUM_BODIES, ACTION_DIM, config, world_model=WorldModel(NUM_BODIES, ACTION_DIM, (16,)))
        if compile_it:
            vae.compile()
        losses.append([vae.update(batch)["loss"] for _ in range(3)])
    assert losses[1] == pytest.approx(losses[0], rel=1e-5)


def test_a_compile_that_fails_leaves_the_learner_eager_with_the_same_draws(monkeypatch, caplog) -> None:
    """Where torch.compile cannot build the loss (here: it raises, as it does on a machine without a C++
    compiler), the first update runs the eager loss with the draws made for it, logs one line, and every
    later update is eager too: the same updates as a learner never compiled."""
    calls = []

    def failing_compile(fn, **_):
        def compiled(*args, **kwargs):
            calls.append(1)
            raise RuntimeError("InductorError: CppCompileError: no C++ compiler\nmore detail")

        return compiled

    states = _batch(n=8, t=3).states
    batch = VAEBatch(states, states.clone())

    eager, fallen_back = _vae_learner(), _vae_learner()
    monkeypatch.setattr(torch, "compile", failing_compile)
    fallen_back.compile()
    with caplog.at_level("WARNING", logger="workers.learners.base"):
        runs = [[vae.update(batch)["loss"] for _ in range(3)] for vae in (eager, fallen_back)]
    assert runs[1] == runs[0]  # the same draws, the same losses, update after update
    assert len(calls) == 1  # compiled once, not again after it failed
    (line,) = [r.getMessage() for r in caplog.records]
    expected = "RuntimeError: InductorError: CppCompileError: no C++ compiler"  # the error's first line
    assert line == f"vae: torch.compile failed, the loss stays eager: {expected}"
    for p_eager, p_other in zip(eager.parameters(), fallen_back.parameters(), strict=True):
        torch.testing.assert_close(p_other, p_eager, rtol=0, atol=0)
