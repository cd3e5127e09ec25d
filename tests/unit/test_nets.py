"""The shared building blocks: the input normaliser's statistics and its kept conversion."""

from __future__ import annotations

import copy
import pickle

import torch

from workers.learners.base import OPTIMIZERS, make_optimizer
from workers.models.nets import Normalizer, mlp


def by_formula(norm: Normalizer, x: torch.Tensor) -> torch.Tensor:
    return (x - norm.mean.to(x.dtype)) / norm.std.to(x.dtype)


def test_the_normaliser_follows_every_change_of_its_statistics():
    """The float32 mean and std are kept between calls; each way the statistics change must reach the output."""
    g = torch.Generator().manual_seed(0)
    norm, x = Normalizer(3), torch.randn(5, 3, generator=g)
    assert norm(x) is x and norm.denormalize(x) is x  # no samples yet
    norm.update(2 * torch.randn(100, 3, generator=g) + 1)
    first = norm(x)
    assert torch.equal(first, by_formula(norm, x)) and torch.equal(norm(x), first)
    for _ in range(300):  # past the small integers Python keeps as one object each
        norm.update(torch.randn(4, 3, generator=g))
    assert torch.equal(norm(x), by_formula(norm, x)) and not torch.equal(norm(x), first)
    norm.load_state_dict(
        {"count": torch.tensor(4.0).double(), "mean": torch.ones(3).double(), "m2": torch.ones(3).double() * 16}
    )
    torch.testing.assert_close(norm(x), (x - 1) / 2)
    torch.testing.assert_close(norm.denormalize(norm(x)), x)
    with torch.no_grad():
        norm.mean.fill_(3.0)  # an in-place write
    torch.testing.assert_close(norm(x), (x - 3) / 2)
    copied = pickle.loads(pickle.dumps(norm))
    assert copied._cached is None and torch.equal(copied(x), norm(x))
    assert torch.equal(copy.deepcopy(norm)(x), norm(x))
    assert norm(x.double()).dtype == torch.float64


def test_the_normaliser_is_differentiable_after_an_inference_call():
    norm = Normalizer(3)
    norm.update(torch.randn(10, 3))
    with torch.inference_mode():
        norm(torch.randn(2, 3))
    x = torch.randn(2, 3, requires_grad=True)
    (grad,) = torch.autograd.grad(norm(x).sum(), x)
    torch.testing.assert_close(grad, (1 / norm.std.float()).expand(2, 3))


def test_every_optimiser_takes_the_step_of_its_per_parameter_implementation():
    """make_optimizer uses torch's multi-tensor (foreach) kernels; three steps land where the plain loop's do."""
    for name in OPTIMIZERS:
        torch.manual_seed(0)
        nets = [mlp(6, (16, 16), 3) for _ in range(2)]
        nets[1].load_state_dict(nets[0].state_dict())
        options = {"momentum": 0.9} if name == "sgd" else {}
        fast = make_optimizer(name, nets[0].parameters(), 1e-2, weight_decay=1e-3, **options)
        plain = OPTIMIZERS[name](nets[1].parameters(), lr=1e-2, foreach=False, weight_decay=1e-3, **options)
        assert fast.defaults["foreach"] is True
        start = [p.detach().clone() for p in nets[0].parameters()]
        x = torch.randn(32, 6)
        for _ in range(3):
            for net, opt in zip(nets, (fast, plain), strict=True):
                opt.zero_grad()
                net(x).square().mean().backward()
                opt.step()
        moved = [(a - b).abs().max() for a, b in zip(nets[0].parameters(), start, strict=True)]
        assert max(moved) > 1e-4, name
        for a, b in zip(nets[0].parameters(), nets[1].parameters(), strict=True):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
