"""What every learner shares: the update step with its safety checks, versioned weights, state dicts.

A learner owns its networks and optimiser. `update(batch)` computes the loss
(a pure function from `workers.losses`), takes one optimiser step and returns
flat float metrics; the caller namespaces them (`world_model/loss`, ...).

Safety:
- A non-finite loss or gradient norm skips the step (the optimiser state is
  untouched) and counts it in `skipped_updates`.
- `get_weights()` never returns a non-finite tensor: when the current
  parameters are not all finite it returns the last good weights it published,
  or raises `NonFiniteWeightsError` if there are none.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

log = logging.getLogger(__name__)


class NonFiniteWeightsError(RuntimeError):
    pass


class DeviceError(RuntimeError):
    """A learner was asked for a device this process does not have."""


DEVICES = ("auto", "cpu", "cuda")
COMPILE_MODES = ("eager", "default", "reduce-overhead")  # runtime.learner_compile: `Learner.compile`'s modes


@contextmanager
def cpu_seeded(seed: int) -> Iterator[None]:
    """Inside: the CPU's global generator (what builds a module's initial weights) seeded with `seed`; after: as it
    was. No GPU's generator is touched: `torch.manual_seed` inside `fork_rng(devices=[])` would reseed every CUDA
    generator and leave them so, making a GPU run's noise depend on the order its parts were built in."""
    with torch.random.fork_rng(devices=[]):
        torch.random.default_generator.manual_seed(seed)
        yield


def resolve_device(setting: str, key: str = "runtime.learner_device") -> torch.device:
    """The device a learner computes on, from its setting: "cpu"; "cuda", the first GPU this process sees (under
    Ray, the one assigned to the actor: Ray sets CUDA_VISIBLE_DEVICES), refused when it sees none; "auto",
    that GPU when there is one, else the CPU."""
    if setting not in DEVICES:
        raise ValueError(f"{key}: unknown device {setting!r}; expected one of {DEVICES}")
    if setting == "cpu":
        return torch.device("cpu")
    if torch.cuda.is_available():
        return torch.device("cuda", torch.cuda.current_device())
    if setting == "cuda":
        raise DeviceError(f"{key}=cuda: this process sees no GPU (torch {torch.__version__}, CUDA available: False)")
    return torch.device("cpu")


@dataclass(frozen=True)
class Weights:
    """A snapshot of a learner's module state, tagged with the update count that made it."""

    version: int
    state: dict[str, torch.Tensor]


@dataclass
class Schedule:
    """A scalar that changes with the update count.

    kind:
      constant  - `start` throughout.
      linear    - from `start` to `end` over `steps` updates, then `end`.
      staircase - from `start` to `end` in equal steps, one every `every` updates,
                  reaching `end` after `steps` updates (ControlVAE raises β this way).
      exp       - `start` multiplied by `factor` every `every` updates, never past
                  `end` when it is given (PhysicsVAE's learning-rate decay, 0.7 every 50 epochs).
    """

    start: float
    end: float | None = None
    kind: str = "constant"
    steps: int = 1
    every: int = 1
    factor: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("constant", "linear", "staircase", "exp"):
            raise ValueError(f"unknown schedule kind {self.kind!r}")
        if self.steps < 1 or self.every < 1:
            raise ValueError("schedule steps and every must be at least 1")

    def __call__(self, step: int) -> float:
        end = self.start if self.end is None else self.end
        if self.kind == "constant":
            return self.start
        if self.kind == "linear":
            return self.start + (end - self.start) * min(step / self.steps, 1.0)
        if self.kind == "staircase":
            stairs = max(self.steps // self.every, 1)
            k = min(step // self.every, stairs)
            return self.start + (end - self.start) * k / stairs
        value = self.start * self.factor ** (step // self.every)
        if self.end is not None:
            value = max(value, self.end) if self.factor < 1 else min(value, self.end)
        return value


def all_finite(tensors: Iterable[torch.Tensor]) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors if t.is_floating_point())


def _floating(x: Any) -> bool:
    """A floating-point tensor or NumPy array."""
    if isinstance(x, torch.Tensor):
        return x.is_floating_point()
    return isinstance(x, np.ndarray) and x.dtype.kind == "f"


def as_tensor(x: Any, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
    """x as a tensor (floating point as `dtype`) on `device` (where it is, when None). A CPU batch bound for a
    GPU goes through pinned memory with a non-blocking copy."""
    t = (
        (x.to(dtype) if x.is_floating_point() else x)
        if isinstance(x, torch.Tensor)
        else torch.as_tensor(x, dtype=dtype)
    )
    if device is None:
        return t
    device = torch.device(device)
    if device.type == "cuda" and t.device.type == "cpu" and not torch.compiler.is_compiling():
        return t.pin_memory().to(device, non_blocking=True)  # (a compiled graph cannot pin: it copies plainly)
    return t.to(device)


class Learner:
    """Base class. Subclasses set `self.module` and `self.optimizer` and implement `loss(batch)`.

    `loss` returns (total, {name: term}); terms are reported as floats under their names.
    """

    name = "learner"
    double_backward = False  # the loss takes a gradient of a gradient (torch.compile cannot trace it)

    def __init__(
        self,
        module: nn.Module,
        optimizer: torch.optim.Optimizer,
        grad_clip: float | None = None,
        device: torch.device | str = "cpu",
    ):
        """`device`: where the module, its optimiser state and every batch live (`resolve_device`); weights are
        published and checkpoints written as CPU tensors all the same, and load on either device."""
        self.device = torch.device(device)
        self.module = module.to(self.device)
        self.optimizer = optimizer
        self.grad_clip = grad_clip
        self.version = 0
        self.skipped_updates = 0
        self._published: Weights | None = None

    def compile(self, mode: str | None = None) -> None:
        """Have `update` call the loss through `torch.compile` (`mode`: None for the default, or e.g.
        "reduce-overhead" for CUDA graphs): the same loss and gradients to float rounding, fewer kernels and
        less Python per update, after a compile of seconds to a minute on the first update (and again when a
        shape changes: shapes are compiled static). The loss stays the pure function it was; only its caller
        changes."""
        if self.double_backward:
            raise ValueError(f"{self.name}: its loss takes a gradient of a gradient, which torch.compile cannot")
        eager = self.loss
        compiled = torch.compile(eager, mode=mode, dynamic=False)

        def first(batch: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
            # The first call compiles. Where that fails (no C++ compiler on the machine, an operator Inductor
            # cannot lower) the learner goes on eager, the same loss, and the log says so once.
            batch, inputs = self.on_device(batch), self.loss_inputs(batch)
            try:
                out = compiled(batch, **inputs)
            except Exception as e:  # noqa: BLE001 (any failure to compile; the eager call below re-raises the loss's own)
                log.warning("%s: torch.compile failed, the loss stays eager: %s", self.name, _first_line(e))
                self.loss = lambda batch: eager(self.on_device(batch), **self.loss_inputs(batch))
                return eager(batch, **inputs)
            self.loss = loss
            return out

        def loss(batch: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
            # the copies to the device, the random draws and the schedules stay outside the graph
            return compiled(self.on_device(batch), **self.loss_inputs(batch))

        self.loss = first

    def loss_inputs(self, batch: Any) -> dict[str, Any]:
        """What `loss(batch)` would read from the learner's changing state (its random draws, a weight on a
        schedule), made here and given to it as keyword arguments by a compiled loss, whose graph can neither
        draw from a generator nor read a count without recompiling when it changes (`VAELearner`). None here."""
        return {}

    def on_device(self, batch: Any) -> Any:
        """The batch (a dataclass) with its floating-point arrays as float32 tensors on this learner's device,
        as `loss` would make them; its other fields, and a batch of another type, as they are."""
        if not dataclasses.is_dataclass(batch):
            return batch
        moved = {}
        for field in dataclasses.fields(batch):
            x = getattr(batch, field.name)
            if _floating(x):
                moved[field.name] = self.tensor(x)
        return dataclasses.replace(batch, **moved)

    # The step ----------------------------------------------------------------
    def loss(self, batch: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        raise NotImplementedError

    def before_update(self, batch: Any) -> None:
        """Hook: update input statistics, schedules, ... before the loss is computed."""

    def parameters(self) -> list[nn.Parameter]:
        return [p for p in self.module.parameters() if p.requires_grad]

    def update(self, batch: Any) -> dict[str, float]:
        self.module.train()
        self.before_update(batch)
        total, terms = self.loss(batch)
        metrics = {k: float(v.detach()) if isinstance(v, torch.Tensor) else float(v) for k, v in terms.items()}
        metrics["loss"] = float(total.detach())
        self.optimizer.zero_grad(set_to_none=True)
        if not math.isfinite(metrics["loss"]):
            return self._skip(metrics)
        total.backward()
        params = self.parameters()
        clip = self.grad_clip if self.grad_clip else float("inf")
        grad_norm = float(torch.nn.utils.clip_grad_norm_(params, clip, foreach=True))
        if not math.isfinite(grad_norm):
            self.optimizer.zero_grad(set_to_none=True)
            return self._skip(metrics)
        self.optimizer.step()
        self.version += 1
        self.after_update()
        metrics["grad_norm"] = grad_norm
        metrics["lr"] = self.optimizer.param_groups[0]["lr"]
        metrics["skipped_updates"] = float(self.skipped_updates)
        return metrics

    def after_update(self) -> None:
        """Hook: schedules that depend on the update count."""

    def _skip(self, metrics: dict[str, float]) -> dict[str, float]:
        self.skipped_updates += 1
        metrics["skipped_updates"] = float(self.skipped_updates)
        return metrics

    # Weights -----------------------------------------------------------------
    def get_weights(self) -> Weights:
        """The module's state (CPU copies) and its version; never non-finite."""
        if self._published is not None and self._published.version == self.version:
            return self._published
        state = {k: v.detach().to("cpu", copy=True) for k, v in self.module.state_dict().items()}
        if not all_finite(state.values()):
            if self._published is None:
                raise NonFiniteWeightsError(f"{self.name}: weights hold non-finite values and none were published")
            return self._published
        self._published = Weights(self.version, state)
        return self._published

    def set_weights(self, weights: Weights) -> None:
        self.module.load_state_dict(weights.state)
        self.version = weights.version

    # Checkpoints -------------------------------------------------------------
    def tensor(self, x: Any, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """A batch's array as a tensor on this learner's device."""
        return as_tensor(x, dtype, self.device)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: module, optimiser, counters. CPU tensors and plain types only, so that
        a checkpoint from one device loads on another."""
        return {
            "module": _to_cpu(self.module.state_dict()),
            "optimizer": _to_cpu(self.optimizer.state_dict()),
            "version": self.version,
            "skipped_updates": self.skipped_updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.module.load_state_dict(state["module"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.version = int(state["version"])
        self.skipped_updates = int(state["skipped_updates"])
        self._published = None


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return f"{type(e).__name__}: {text.splitlines()[0] if text else ''}"


def _to_cpu(x: Any) -> Any:
    """Every tensor in a nested dict or list moved to the CPU (the others as they are)."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu()
    if isinstance(x, dict):
        return {k: _to_cpu(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return type(x)(_to_cpu(v) for v in x)
    return x


OPTIMIZERS = {"adam": torch.optim.Adam, "radam": torch.optim.RAdam, "adamw": torch.optim.AdamW, "sgd": torch.optim.SGD}


def make_optimizer(
    name: str, params: Iterable[nn.Parameter] | list[dict], lr: float, **options
) -> torch.optim.Optimizer:
    """The optimiser `name` over `params` (tensors or parameter groups), with its multi-tensor implementation:
    one kernel per step of the update rule for all parameters rather than one per parameter (on a GPU torch
    picks it by itself; on the CPU it does not, and at our sizes the per-parameter loop costs more than the
    arithmetic). The same update rule, to float rounding."""
    try:
        return OPTIMIZERS[name](params, lr=lr, foreach=True, **options)
    except KeyError:
        raise ValueError(f"unknown optimizer {name!r}; expected one of {sorted(OPTIMIZERS)}") from None
