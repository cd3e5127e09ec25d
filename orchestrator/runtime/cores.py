"""Which CPU cores each actor runs on (`runtime.pin_cores`), when the run has Ray on this machine to itself.

The default ControlVAE loop on a laptop is learner-bound: every iteration waits for the VAE learner's
updates, while the world-model learner, the rollout workers and the replay buffer have time to spare.
Left to the scheduler, five busy processes share the cores, the VAE's updates are interrupted and its
caches refilled, and the loop runs at the pace of the slowest share. A method names the components the
loop waits on (`Component.own_core`); with `pin_cores=auto` each of them is given a core of its own and
every other actor the cores left, so that the critical path never waits for a core (`plan`). Measured on
2 cores, default run (README, "Learners on their own cores"): 1.3-1.4x the samples per second.

Pinning is by the Linux scheduler's CPU affinity (`os.sched_setaffinity`); where there is none (macOS),
or too few cores to leave one for the rest, nothing is pinned and the log says why.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

log = logging.getLogger(__name__)

PIN_MODES = ("auto", "shared")  # not "off": YAML reads that as false


def available() -> list[int]:
    """The cores this process may run on, in order; [] where the platform cannot pin."""
    if not hasattr(os, "sched_getaffinity"):
        return []
    return sorted(os.sched_getaffinity(0))


def plan(cores: Sequence[int], own: Sequence[str], shared: Sequence[str]) -> dict[str, tuple[int, ...]]:
    """The cores of each actor: one of its own for each name in `own` (the highest-numbered cores, in
    order), the rest shared by every name in `shared`. {} when that would leave no core for the rest,
    or when no actor asks for a core of its own.

    plan([0, 1], ["vae"], ["replay", "rollout-0"]) == {"vae": (1,), "replay": (0,), "rollout-0": (0,)}
    """
    if not own or len(cores) < len(own) + 1:
        return {}
    rest, mine = tuple(cores[: len(cores) - len(own)]), cores[len(cores) - len(own) :]
    pinned = {name: (core,) for name, core in zip(own, mine, strict=True)}
    pinned.update({name: rest for name in shared})
    return pinned


def pin(cores: Sequence[int]) -> None:
    """Run every thread of this process, and the threads and processes it starts later, on `cores`."""
    for task in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(task), cores)
        except ProcessLookupError:  # a thread that ended meanwhile
            pass


def pinned(cls: type, cores: Sequence[int]) -> type:
    """`cls` whose instances pin their process to `cores` before they are built (again after a restart:
    a restarted Ray actor builds its instance anew)."""
    cores = tuple(cores)

    def __init__(self, *args, **kwargs) -> None:
        pin(cores)
        cls.__init__(self, *args, **kwargs)

    return type(cls.__name__, (cls,), {"__init__": __init__, "__doc__": cls.__doc__})


def assign(runtime_cfg, own: Sequence[str], shared: Sequence[str]) -> dict[str, tuple[int, ...]]:
    """`plan` over this machine's cores when `runtime.pin_cores` is auto and Ray is started for the run here
    (a cluster's nodes are shared: nothing is pinned there, nor in the local runtime's single process);
    the assignment, or why there is none, in the log."""
    from orchestrator.runtime.base import uses_ray

    r = runtime_cfg
    if r.pin_cores == "shared" or not uses_ray(r) or r.address or not own:
        return {}
    cores = available()
    pinned_cores = plan(cores, own, shared)
    if not pinned_cores:
        log.info("runtime.pin_cores: %d core(s) cannot give %s one each and the rest one: none pinned", len(cores), own)
        return {}
    rest = pinned_cores[shared[0]] if shared else ()
    mine = ", ".join(f"{name} on core {pinned_cores[name][0]}" for name in own)
    log.info("runtime.pin_cores: %s; the other actors on cores %s", mine, ",".join(map(str, rest)))
    return pinned_cores
