"""A stand-in GPU for a machine without one: tensors that hold real values, computed on the CPU, but say they are
on another device (`DEVICE`, PyTorch's `meta`), and refuse, as CUDA does, any operation that mixes them with CPU
tensors (0-dimensional ones aside, which CUDA takes too), `.numpy()`, and a draw from a generator of the other
device (a CPU generator filling a GPU tensor, or the reverse).

    with stand_in_gpu():
        learner = build(DEVICE)          # its networks, optimizer and generators "on the GPU"
        learner.update(batch)            # a CPU batch moved where it should be, or a RuntimeError naming the op

Why `meta` and not fake CUDA tensors: on a CPU-only build of torch, C++ code that guards a CUDA device (the
composite `linear`, for one) aborts the process, and fake tensors hold no values, so nothing that reads one (a
normaliser's first-batch branch, a learner's metrics) runs. The meta device has a guard that does nothing, and
these tensors keep their values inside (`OnDevice.inner`).

What it cannot catch: kernels only CUDA has, and their numerics; torch.compile's graphs; the memory MuJoCo Warp
shares with torch, and Warp's own tensors on a GPU (on Warp's CPU device they are CPU tensors, the mirror case);
anything that states its device as the string "cuda" (it is "meta" here).

It patches, while it is on: module conversion to swap parameters (`torch.__future__`), torch's foreach
support check to take the meta device, and `torch.Generator(device=meta)` to give a CPU generator (the values are
drawn on the CPU). A test helper only.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator

import torch
import torch.utils._foreach_utils as foreach_utils
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map

DEVICE = torch.device("meta")
_MOVES = (torch.ops.aten._to_copy.default, torch.ops.aten.copy_.default)


class OnDevice(torch.Tensor):
    """A tensor on the stand-in device: its metadata says `DEVICE`, its values are `inner`, on the CPU."""

    inner: torch.Tensor

    @staticmethod
    def __new__(cls, inner: torch.Tensor):
        r = torch.Tensor._make_wrapper_subclass(
            cls, inner.size(), strides=inner.stride(), storage_offset=inner.storage_offset(), dtype=inner.dtype,
            device=DEVICE, requires_grad=inner.requires_grad, layout=inner.layout,
        )  # fmt: skip
        r.inner = inner
        return r

    def __repr__(self) -> str:
        return f"OnDevice({self.inner!r})"

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        return _run(func, args, kwargs or {})


def _on_device(device) -> bool | None:
    return None if device is None else torch.device(device).type == DEVICE.type


def _run(func, args, kwargs):
    seen = set()

    def see(x):
        if isinstance(x, OnDevice):
            seen.add("device")
        elif isinstance(x, torch.Tensor) and x.dim() > 0:
            seen.add(x.device.type)

    tree_map(see, (args, kwargs))
    if "device" in seen and len(seen) > 1 and func not in _MOVES:
        raise RuntimeError(f"{func}: tensors on the GPU and on the {'/'.join(sorted(seen - {'device'}))} mixed")
    wanted = _on_device(kwargs.get("device"))
    generator = kwargs.get("generator")
    if generator is not None and (generator._cdata in _DEVICE_GENERATORS) != bool(wanted or "device" in seen):
        where = "GPU" if generator._cdata in _DEVICE_GENERATORS else "cpu"
        raise RuntimeError(f"{func}: a generator on the {where} drawing for the other device (CUDA refuses it)")
    unwrapped_args = tree_map(lambda x: x.inner if isinstance(x, OnDevice) else x, args)
    unwrapped_kwargs = tree_map(lambda x: x.inner if isinstance(x, OnDevice) else x, kwargs)
    if wanted:
        unwrapped_kwargs["device"] = torch.device("cpu")
    out = func(*unwrapped_args, **unwrapped_kwargs)
    on = wanted if wanted is not None else "device" in seen
    if on and args and isinstance(args[0], OnDevice) and isinstance(out, torch.Tensor) and out is args[0].inner:
        return args[0]  # in place: the tensor it was given
    return tree_map(lambda x: OnDevice(x) if on and isinstance(x, torch.Tensor) else x, out)


class _Dispatch(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        return _run(func, args, kwargs or {})


def _target(args, kwargs) -> torch.device | None:
    for x in (*args[1:], kwargs.get("device")):
        if isinstance(x, str | torch.device):
            return torch.device(x)
        if isinstance(x, torch.Tensor):
            return x.device
    return None


class _Moves(TorchFunctionMode):
    """`Tensor.to(DEVICE)` and `copy_` between the two, which torch's front end would make meta tensors of (no
    values): done as the copies they are."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is torch.Tensor.to and not isinstance(args[0], OnDevice) and _on_device(_target(args, kwargs)):
            src = args[0]
            dtype = next((a for a in args[1:] if isinstance(a, torch.dtype)), kwargs.get("dtype", src.dtype))
            with torch._C.DisableTorchFunctionSubclass():
                return OnDevice(src.detach().to(dtype=dtype).clone())
        if func is torch.Tensor.copy_ and isinstance(args[0], OnDevice) != isinstance(args[1], OnDevice):
            dst, src = args[0], args[1]
            (dst.inner if isinstance(dst, OnDevice) else dst).copy_(src.inner if isinstance(src, OnDevice) else src)
            return dst
        return func(*args, **kwargs)


_GENERATOR = torch.Generator


# Those made "on the GPU", by their C++ object (the dispatcher hands on another Python object for the same generator),
# held while the stand-in is on.
_DEVICE_GENERATORS: dict[int, torch.Generator] = {}


class _Generator:
    """torch.Generator, on the CPU for the stand-in device (a class, as annotations `torch.Generator | None` need);
    one made for the stand-in device is remembered, so that a draw on the wrong side of the two is refused."""

    def __new__(cls, device=None):
        if device is not None and _on_device(device):
            generator = _GENERATOR()
            _DEVICE_GENERATORS[generator._cdata] = generator
            return generator
        return _GENERATOR() if device is None else _GENERATOR(device=device)


@contextlib.contextmanager
def stand_in_gpu() -> Iterator[None]:
    """The stand-in device, for the code run inside."""
    swap = torch.__future__.get_swap_module_params_on_conversion()
    supported = foreach_utils._device_has_foreach_support
    holders = [m for n, m in list(sys.modules.items()) if n.startswith("torch") and
               getattr(m, "_device_has_foreach_support", None) is supported]  # fmt: skip
    torch.__future__.set_swap_module_params_on_conversion(True)
    for m in holders:
        m._device_has_foreach_support = lambda device: _on_device(device) or supported(device)
    torch.Generator = _Generator
    try:
        with _Dispatch(), _Moves():
            yield
    finally:
        torch.Generator = _GENERATOR
        _DEVICE_GENERATORS.clear()
        for m in holders:
            m._device_has_foreach_support = supported
        torch.__future__.set_swap_module_params_on_conversion(swap)
