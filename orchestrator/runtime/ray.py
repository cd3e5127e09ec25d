"""Components as Ray actors: named, reserved together in a placement group, restarted when they die.

The only module that imports ray. A Ray started for the run binds its dashboard to
127.0.0.1 and keeps Ray's token authentication on; `address` joins an existing
cluster instead ("auto" or "ray://host:port").
"""

from __future__ import annotations

import logging
import os
import socket
import time
import uuid
from typing import Any

import ray
from ray.util.placement_group import placement_group, remove_placement_group
from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

from orchestrator.runtime.base import Resources, Runtime
from orchestrator.runtime.cores import pinned, release
from orchestrator.schema import ConfigError

log = logging.getLogger(__name__)

RAY_CLIENT_PORT = 10001  # `ray://host` without a port


class AddressError(ConnectionError):
    """`runtime.address` names no Ray cluster that answers; the message names the address."""


def check_address(address: str, timeout_s: float) -> None:
    """AddressError unless something accepts a TCP connection at `address` within `timeout_s`.

    `ray.init` itself retries an address where nothing answers for minutes; this probe says so at
    once (connection refused) or after `timeout_s` (no route, a firewall). "auto" is looked up as
    `ray.init` would (RAY_ADDRESS, then the cluster `ray start` left on this machine); "local" starts
    a new Ray and is not probed. A port that answers but is no Ray is left to `ray.init`.
    """
    if address == "local":
        return
    key = f"runtime.address={address}"
    target = address
    if address == "auto":
        from ray._private.services import get_ray_address_from_environment

        try:
            target = get_ray_address_from_environment("auto", None)
        except Exception as e:  # a private helper: never let it be the error
            log.debug("could not look up runtime.address=auto (%s)", e)
            return
        if not target:
            raise AddressError(f"{key}: no running Ray cluster found (no RAY_ADDRESS, and `ray start` runs none here)")
    scheme, _, rest = target.rpartition("://")
    if scheme not in ("", "ray"):
        raise AddressError(f"{key}: not a Ray address (host:port, ray://host:port or auto)")
    host, _, port = rest.rpartition(":")
    if not port.isdigit():
        host, port = (rest, str(RAY_CLIENT_PORT)) if scheme == "ray" else (rest, "")
    if not port or not host:
        raise AddressError(f"{key}: no port (the head node's GCS port, 6379 by default: host:6379)")
    host = host.strip("[]")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except TimeoutError:
        raise AddressError(f"{key}: nothing answered at {host}:{port} within {timeout_s:g} s") from None
    except OSError as e:
        reason = (e.strerror or type(e).__name__).lower()
        raise AddressError(f"{key}: no Ray cluster at {host}:{port} ({reason}); is it up (`ray status`)?") from None


class RayRuntime(Runtime):
    name = "ray"

    def __init__(
        self,
        address: str | None = None,
        object_store_mb: int = 512,
        torch_threads: int = 1,
        placement_timeout_s: float = 120.0,
        placement: str = "PACK",
        connect_timeout_s: float = 20.0,
        **_: Any,
    ):
        self.started = not ray.is_initialized()
        self.connect_timeout_s = connect_timeout_s
        self.namespace = f"mocap-{uuid.uuid4().hex[:8]}"
        self.placement_timeout_s = placement_timeout_s
        self.placement = placement
        env = {"env_vars": {"OMP_NUM_THREADS": str(torch_threads), "MKL_NUM_THREADS": str(torch_threads)}}
        self._init_kwargs: dict[str, Any] = {"namespace": self.namespace, "runtime_env": env, "log_to_driver": False}
        if address:
            self._init_kwargs["address"] = address
        else:
            # "local": a new Ray for this run, even where `ray start` left a cluster running on this machine.
            self._init_kwargs.update(
                address="local",
                include_dashboard=True,
                dashboard_host="127.0.0.1",
                object_store_memory=object_store_mb * 2**20,
            )
        self.context = None
        self.group = None
        self._next_bundle = 0
        self._warned_state_api = False

    def reserve(self, bundles: list[Resources]) -> None:
        """Start Ray if needed and reserve every component's resources at once (a placement group)."""
        if not ray.is_initialized():
            if self._init_kwargs["address"] == "local":
                # Logical CPUs: enough for every component even on a laptop with fewer cores.
                need = sum(b.cpus for b in bundles)
                self._init_kwargs["num_cpus"] = max(os.cpu_count() or 1, int(need + 0.999))
            else:
                check_address(self._init_kwargs["address"], self.connect_timeout_s)
            self.context = ray.init(**self._init_kwargs)
        gpus = sum(b.gpus for b in bundles)
        have = ray.cluster_resources().get("GPU", 0.0)
        if gpus > have:  # Ray would wait for the placement group without end
            raise ConfigError(
                f"runtime.learner_gpus, runtime.worker_gpus: the learners, rollout workers and driver ask for "
                f"{gpus:g} GPU(s) in all, the Ray cluster has {have:g}"
            )
        specs = [{"CPU": b.cpus, **({"GPU": b.gpus} if b.gpus else {})} for b in bundles]
        self.group = placement_group(specs, strategy=self.placement)
        ready, _ = ray.wait([self.group.ready()], timeout=self.placement_timeout_s)
        if not ready:
            raise RuntimeError(
                f"Ray could not reserve {specs} within {self.placement_timeout_s:.0f} s: "
                f"cluster resources {ray.available_resources()}"
            )

    def spawn(self, cls: type, *args: Any, name: str, resources: Resources | None = None, **kwargs: Any) -> Any:
        res = resources or Resources()
        options: dict[str, Any] = {
            "name": name,
            "num_cpus": res.cpus,
            "num_gpus": res.gpus,
            "max_restarts": res.max_restarts,
            "max_task_retries": -1 if res.max_restarts else 0,
        }
        if self.group is not None:
            options["scheduling_strategy"] = PlacementGroupSchedulingStrategy(self.group, self._next_bundle)
            self._next_bundle += 1
        if res.cores:
            cls = pinned(cls, res.cores)
        return ray.remote(cls).options(**options).remote(*args, **kwargs)

    def call(self, handle: Any, method: str, *args: Any, **kwargs: Any) -> Any:
        return getattr(handle, method).remote(*args, **kwargs)

    def get(self, futures: Any) -> Any:
        return ray.get(futures)

    def ready(self, futures: list[Any]) -> list[Any]:
        done, _ = ray.wait(list(futures), num_returns=len(futures), timeout=0)
        return done

    def put(self, obj: Any) -> Any:
        return ray.put(obj)

    def kill(self, handle: Any, timeout_s: float = 60.0) -> None:
        """Kill an actor as a crash would, and return once Ray has restarted it (its restart count
        went up), so that calls made after this one never reach the old life."""
        before = self.restarts(handle)
        ray.kill(handle, no_restart=False)
        deadline = time.monotonic() + timeout_s
        while self.restarts(handle) <= before and time.monotonic() < deadline:
            time.sleep(0.1)

    def restarts(self, handle: Any) -> int:
        """Ray's restart count of an actor; 0 (said once) when the state API is unreachable
        (a Ray started without its dashboard)."""
        from ray.util.state import get_actor
        from ray.util.state.exception import RayStateApiException

        try:
            # The dashboard of this run's Ray by address: with several Ray instances on one machine
            # (a cluster, tests) the state API cannot guess which.
            state = get_actor(handle._actor_id.hex(), address=self.dashboard_url())
        except (RayStateApiException, ConnectionError) as e:
            if not self._warned_state_api:
                log.warning("actor restart counts unavailable (%s); reporting 0", type(e).__name__)
                self._warned_state_api = True
            return 0
        return int(getattr(state, "num_restarts", 0) or 0) if state is not None else 0

    def dashboard_url(self) -> str | None:
        url = getattr(self.context, "dashboard_url", None)
        return f"http://{url}" if url and not url.startswith("http") else url

    def shutdown(self) -> None:
        release()  # the cores this run held for its own (runtime.pin_cores), for the next run
        if self.group is not None:
            remove_placement_group(self.group)
            self.group = None
        if self.started and ray.is_initialized():
            ray.shutdown()
