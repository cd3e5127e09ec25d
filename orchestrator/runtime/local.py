"""Every component in this process, called in the order the loop calls them: deterministic for a seed."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from orchestrator.runtime.base import Resources, Runtime


@dataclass
class Done:
    """A future whose value is already there: local calls run when they are made."""

    value: Any


def _resolve(x: Any) -> Any:
    return x.value if isinstance(x, Done) else x


class LocalRuntime(Runtime):
    name = "local"

    def __init__(self, **_: Any):
        self.components: dict[str, Any] = {}

    def spawn(self, cls: type, *args: Any, name: str, resources: Resources | None = None, **kwargs: Any) -> Any:
        obj = cls(*args, **kwargs)
        self.components[name] = obj
        return obj

    def call(self, handle: Any, method: str, *args: Any, **kwargs: Any) -> Done:
        args = tuple(_resolve(a) for a in args)
        kwargs = {k: _resolve(v) for k, v in kwargs.items()}
        return Done(getattr(handle, method)(*args, **kwargs))

    def get(self, futures: Any) -> Any:
        if isinstance(futures, list):
            return [_resolve(f) for f in futures]
        return _resolve(futures)

    def ready(self, futures: list[Any]) -> list[Any]:
        return list(futures)

    def put(self, obj: Any) -> Any:
        return obj

    def kill(self, handle: Any) -> None:
        raise RuntimeError("the local runtime cannot kill a component: it runs in this process")
