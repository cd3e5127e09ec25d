"""What an update's matmuls cost: recorded with their FLOPs as one update dispatches them, replayed alone on
operands of the same shapes and strides, and the device's dense-GEMM peak to hold them against
(`orchestrator.bench.learners` describes the method)."""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map
from torch.utils.flop_counter import flop_registry

CPU = torch.device("cpu")


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (a no-op on the CPU), so that a clock reads what was done."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def machine_peak(device: torch.device, seconds: float = 1.0) -> float:
    """Dense float32 matmul GFLOP/s of this device and thread count: one large square GEMM, median of repeats."""
    n = 4096 if device.type == "cuda" else 2048
    gen = torch.Generator().manual_seed(0)
    a, b = torch.randn(n, n, generator=gen).to(device), torch.randn(n, n, generator=gen).to(device)
    a @ b  # warm up (cuBLAS handles, thread pool)
    sync(device)
    times: list[float] = []
    end = time.perf_counter() + seconds
    while len(times) < 3 or time.perf_counter() < end:
        t0 = time.perf_counter()
        a @ b
        sync(device)
        times.append(time.perf_counter() - t0)
    return 2 * n**3 / statistics.median(times) / 1e9


# Recording the matmuls of one update ------------------------------------------------
@dataclass(frozen=True)
class TensorSpec:
    shape: tuple[int, ...]
    stride: tuple[int, ...]
    dtype: torch.dtype
    device: torch.device = CPU

    def make(self, gen: torch.Generator) -> torch.Tensor:
        """A tensor with this shape and these strides (views, transposes and broadcasts kept) over random values."""
        size = 1 + sum((n - 1) * s for n, s in zip(self.shape, self.stride, strict=True)) if all(self.shape) else 0
        flat = torch.randn(size, generator=gen).to(self.dtype).to(self.device)
        return flat.as_strided(self.shape, self.stride)


def _spec(x: Any) -> Any:
    if isinstance(x, torch.Tensor):
        return TensorSpec(tuple(x.shape), tuple(x.stride()), x.dtype, x.device)
    return x


class MatmulRecorder(TorchDispatchMode):
    """Counts each distinct call of a FLOP-counted operator by (operator, argument shapes and strides)."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: dict[str, list[Any]] = {}  # key -> [op, args spec, kwargs spec, count, FLOPs of one call]
        self.order: list[str] = []  # the keys in the order the update called them

    @property
    def flops(self) -> int:
        return sum(count * flops for *_, count, flops in self.calls.values())

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        count_flops = flop_registry.get(func.overloadpacket)
        if count_flops is not None:
            a, k = tree_map(_spec, args), tree_map(_spec, kwargs)
            key = f"{func}{a}{k}"
            entry = self.calls.setdefault(key, [func, a, k, 0, 0])
            self.order.append(key)
            entry[3] += 1
            entry[4] = count_flops(*args, **kwargs, out_val=out)
        return out


def _label(op: Any, args: Any) -> str:
    shapes = ["x".join(map(str, a.shape)) for a in args if isinstance(a, TensorSpec)]
    return f"{op.overloadpacket.__name__} " + " @ ".join(shapes[-2:]) if shapes else str(op)


class MatmulReplay:
    """The recorded matmuls of one update, replayed alone and in order on operands made once."""

    def __init__(self, recorder: MatmulRecorder, seed: int = 0, device: torch.device = CPU):
        gen = torch.Generator().manual_seed(seed)
        self.sync = (lambda: sync(device)) if device.type == "cuda" else (lambda: None)

        def make(x: Any) -> Any:
            return x.make(gen) if isinstance(x, TensorSpec) else x

        self.calls = {key: (op, tree_map(make, a), tree_map(make, k)) for key, (op, a, k, *_) in recorder.calls.items()}
        self.info = recorder.calls
        self.order = recorder.order
        self.busy = dict.fromkeys(self.calls, 0.0)  # seconds per key, summed over passes
        self.passes = 0
        for op, args, kwargs in self.calls.values():  # touch every operand once
            op(*args, **kwargs)

    def run(self) -> float:
        """One pass over the update's matmuls; the sum of the calls' times."""
        calls, busy, clock, sync = self.calls, self.busy, time.perf_counter, self.sync
        total = 0.0
        for key in self.order:
            op, args, kwargs = calls[key]
            t0 = clock()
            op(*args, **kwargs)
            sync()
            dt = clock() - t0
            busy[key] += dt
            total += dt
        self.passes += 1
        return total

    def top(self, n: int) -> list[dict[str, Any]]:
        """The n matmuls with the most FLOPs per update: calls, GFLOP and their mean rate in the replays."""
        rows = []
        for key, (op, a_spec, _, count, flops) in self.info.items():
            seconds = self.busy[key] / max(self.passes, 1)
            rate = count * flops / seconds / 1e9 if seconds > 0 else float("nan")
            rows.append({"op": _label(op, a_spec), "calls": count, "gflop": count * flops / 1e9, "gflops_per_s": rate})
        return sorted(rows, key=lambda r: -r["gflop"])[:n]
