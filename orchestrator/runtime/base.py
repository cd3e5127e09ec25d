"""What a runtime offers the loop: spawn components, call their methods, wait, share objects.

The loop is written once against this interface; the backend is chosen when the
experiment is built. Components are plain classes; a handle refers to one, and
`call(handle, "method", ...)` returns a future that `get` resolves. Futures and
shared objects may be passed as arguments to other calls.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Resources:
    cpus: float = 1.0
    gpus: float = 0.0
    max_restarts: int = 0


class Runtime:
    name = "base"

    def reserve(self, bundles: list[Resources]) -> None:
        """Reserve every component's resources at once, in spawn order, before the first spawn."""

    def spawn(self, cls: type, *args: Any, name: str, resources: Resources | None = None, **kwargs: Any) -> Any:
        raise NotImplementedError

    def call(self, handle: Any, method: str, *args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError

    def get(self, futures: Any) -> Any:
        raise NotImplementedError

    def ready(self, futures: list[Any]) -> list[Any]:
        """The futures among these that have finished (all of them, locally)."""
        raise NotImplementedError

    def put(self, obj: Any) -> Any:
        """Share an object once; the result can be passed to many calls."""
        raise NotImplementedError

    def kill(self, handle: Any) -> None:
        """Kill a component as a crash would (tests of restarts)."""
        raise NotImplementedError

    def restarts(self, handle: Any) -> int:
        return 0

    def dashboard_url(self) -> str | None:
        return None

    def shutdown(self) -> None:
        pass
