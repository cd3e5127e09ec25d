"""Building blocks shared by every network: MLPs, input normalisation, initialisation."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import torch
from torch import nn

ACTIVATIONS: dict[str, type[nn.Module]] = {"elu": nn.ELU, "relu": nn.ReLU, "tanh": nn.Tanh, "silu": nn.SiLU}


def activation(name: str) -> nn.Module:
    try:
        return ACTIVATIONS[name]()
    except KeyError:
        raise ValueError(f"unknown activation {name!r}; expected one of {sorted(ACTIVATIONS)}") from None


def mlp(
    in_dim: int,
    hidden: Sequence[int],
    out_dim: int,
    act: str = "elu",
    out_scale: float | None = None,
) -> nn.Sequential:
    """Linear layers with `act` between them and none after the last.

    out_scale, when given, scales the last layer's initial weights (a small value
    starts a residual or a policy head near zero) and zeroes its bias.
    """
    layers: list[nn.Module] = []
    d = in_dim
    for h in hidden:
        layers += [nn.Linear(d, h), activation(act)]
        d = h
    last = nn.Linear(d, out_dim)
    if out_scale is not None:
        with torch.no_grad():
            last.weight.mul_(out_scale)
            last.bias.zero_()
    layers.append(last)
    return nn.Sequential(*layers)


class ConcatMLP(nn.Module):
    """An MLP that concatenates a conditioning input to every layer's input.

    ControlVAE re-concatenates s to each layer of the prior and posterior, and z
    to each layer of the policy's experts (with layer norm on the concatenation).
    """

    def __init__(
        self,
        in_dim: int,
        cond_dim: int,
        hidden: Sequence[int],
        out_dim: int,
        act: str = "elu",
        layer_norm: bool = False,
        out_scale: float | None = None,
    ):
        super().__init__()
        dims = [in_dim, *hidden]
        self.layers = nn.ModuleList(nn.Linear(d + cond_dim, h) for d, h in zip(dims[:-1], dims[1:], strict=True))
        self.norms = nn.ModuleList((nn.LayerNorm(d + cond_dim) if layer_norm else nn.Identity()) for d in dims[:-1])
        self.out = nn.Linear(dims[-1] + cond_dim, out_dim)
        if out_scale is not None:
            with torch.no_grad():
                self.out.weight.mul_(out_scale)
                self.out.bias.zero_()
        self.act = activation(act)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        for layer, norm in zip(self.layers, self.norms, strict=True):
            x = self.act(layer(norm(torch.cat((x, cond), dim=-1))))
        return self.out(torch.cat((x, cond), dim=-1))


class PlainMLP(nn.Module):
    """An MLP on the concatenation (x, cond), taken once at its input: `ConcatMLP`'s call, `mlp`'s network
    (PhysicsVAE's encoder and motor decoder, Table 2 and the authors' code)."""

    def __init__(
        self, in_dim: int, cond_dim: int, hidden: Sequence[int], out_dim: int, act: str = "elu",
        out_scale: float | None = None,
    ):  # fmt: skip
        super().__init__()
        self.net = mlp(in_dim + cond_dim, hidden, out_dim, act, out_scale)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat((x, cond), dim=-1))


class Normalizer(nn.Module):
    """Running mean and standard deviation of an input, applied as (x - mean) / std.

    Statistics are accumulated by `update` (rows with a non-finite value are
    ignored) until `max_count` samples have been
    seen, then frozen, so a trained network's input scaling stops moving. They
    live in buffers and therefore in the state dict and in published weights.
    """

    def __init__(self, dim: int, max_count: float = 1e6, eps: float = 1e-2):
        super().__init__()
        self.max_count = max_count
        self.eps = eps
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(dim, dtype=torch.float64))
        self._cached: tuple | None = None  # see `affine`

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        if self.count >= self.max_count:
            return
        x = x.detach().reshape(-1, x.shape[-1]).double()
        x = x[torch.isfinite(x).all(-1)]  # a corrupt sample must not poison the statistics for good
        n = x.shape[0]
        if n == 0:
            return
        mean_b = x.mean(0)
        m2_b = ((x - mean_b) ** 2).sum(0)
        total = self.count + n
        delta = mean_b - self.mean
        self.mean += delta * n / total
        self.m2 += m2_b + delta**2 * self.count * n / total
        self.count.fill_(total)

    @property
    def std(self) -> torch.Tensor:
        var = self.m2 / self.count.clamp(min=1.0)
        return var.sqrt().clamp(min=self.eps)

    def affine(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(mean, std) as `dtype`, or None before any sample. A network applies its normalisers at every step
        of a rollout while the statistics stay put, so the conversion is kept until they change: `update`,
        `load_state_dict` and in-place writes bump the buffers' version counters, `.to()` replaces them."""
        if torch.compiler.is_compiling():  # in a compiled graph: no cache and no branch on the data
            std = torch.where(self.count > 0, self.std, torch.ones_like(self.mean))  # mean is 0 before a sample
            return self.mean.to(dtype), std.to(dtype)
        buffers = (self.count, self.mean, self.m2)
        key = (dtype, torch.is_inference_mode_enabled(), *(t._version for t in buffers))
        cached = self._cached
        if cached is None or cached[1] != key or not all(a is b for a, b in zip(cached[0], buffers, strict=True)):
            with torch.no_grad():
                value = None if self.count == 0 else (self.mean.to(dtype), self.std.to(dtype))
            cached = self._cached = (buffers, key, value)
        return cached[2]

    def __getstate__(self) -> dict:
        return {**super().__getstate__(), "_cached": None}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        affine = self.affine(x.dtype)
        if affine is None:
            return x
        return (x - affine[0]) / affine[1]

    def denormalize(self, y: torch.Tensor) -> torch.Tensor:
        """y · std + mean: a standardised output back in the data's units (unchanged before any sample)."""
        affine = self.affine(y.dtype)
        return y if affine is None else y * affine[1] + affine[0]


def gaussian(
    shape: Sequence[int],
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Standard normal noise of `shape` on `device`, drawn from `generator` on the generator's own device
    (the CPU's default stream when there is none) and then moved.

    A rollout worker's policy may run on a GPU while its random stream stays the CPU generator it
    checkpoints: the draws are then the same numbers on either device, so one seed gives the same noise
    wherever inference runs (on the CPU, exactly `torch.randn(shape, generator=generator)`)."""
    source = generator.device if generator is not None else torch.device("cpu")
    noise = torch.randn(tuple(shape), generator=generator, dtype=dtype, device=source)
    return noise if device is None else noise.to(device)


@contextlib.contextmanager
def evaluation_mode(controller: torch.nn.Module | None) -> Iterator[None]:
    """The module in eval mode and no gradients inside; its mode as it was after."""
    was_training = controller.training if controller is not None else False
    if controller is not None:
        controller.eval()
    try:
        with torch.no_grad():
            yield
    finally:
        if controller is not None:
            controller.train(was_training)
