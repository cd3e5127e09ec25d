"""Which CPU cores each actor runs on (`runtime.pin_cores`), when the run has Ray on this machine to itself.

The default ControlVAE loop on a laptop is learner-bound: every iteration waits for the VAE learner's
updates, while the world-model learner, the rollout workers and the replay buffer have time to spare.
Left to the scheduler, five busy processes share the cores, the VAE's updates are interrupted and its
caches refilled, and the loop runs at the pace of the slowest share. A method names the components the
loop waits on (`Component.own_core`); with `pin_cores=auto` each of them is given a core of its own and
every other actor the cores left, so that the critical path never waits for a core (`plan`). Measured on
2 cores, default run, against the scheduler alone (docs/learners.md): 1.15x the samples per second.

Pinning is by the Linux scheduler's CPU affinity (`os.sched_setaffinity`); where there is none (macOS),
or too few cores to leave one for the rest, nothing is pinned and the log says why.
"""

from __future__ import annotations

import fcntl
import logging
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

log = logging.getLogger(__name__)


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
    the assignment, or why there is none, in the log. Cores that another run on this machine holds for its
    own (a parallel sweep's points, another user's run of this user) are left out, and the cores given here
    are held (`claim`) until `release`, which the Ray runtime calls as it shuts down."""
    from orchestrator.runtime.base import uses_ray

    r = runtime_cfg
    if r.pin_cores == "shared" or not uses_ray(r) or r.address or not own:
        return {}
    cores = [c for c in available() if not held_elsewhere(c)]
    pinned_cores = plan(cores, own, shared)
    if not pinned_cores or not claim([pinned_cores[name][0] for name in own]):
        log.info(
            "runtime.pin_cores: %d free core(s) cannot give %s one each and the rest one: none pinned", len(cores), own
        )
        return {}
    rest = pinned_cores[shared[0]] if shared else ()
    mine = ", ".join(f"{name} on core {pinned_cores[name][0]}" for name in own)
    log.info("runtime.pin_cores: %s; the other actors on cores %s", mine, ",".join(map(str, rest)))
    return pinned_cores


# Claims: one lock file per core, locked (flock) for as long as a run holds the core for its own-core actors;
# the kernel drops the lock when the holding process ends, however it ends.
LOCK_DIR = Path(tempfile.gettempdir()) / f"mocap-orchestrator-cores-{os.getuid() if hasattr(os, 'getuid') else 0}"
_held: dict[int, int] = {}  # core -> the open lock file's descriptor


def _lock(core: int) -> int | None:
    """The descriptor of core's lock file, locked by this call; None when someone holds it."""
    LOCK_DIR.mkdir(mode=0o700, exist_ok=True)
    fd = os.open(LOCK_DIR / f"core-{core}.lock", os.O_RDONLY | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def held_elsewhere(core: int) -> bool:
    """Whether another run (or an earlier claim of this process not yet released) holds `core`."""
    fd = _lock(core)
    if fd is None:
        return True
    os.close(fd)  # closing drops the lock
    return False


def claim(cores: Sequence[int]) -> bool:
    """Hold every core of `cores` until `release`; all or none (False when another run took one first)."""
    fds = {}
    for core in cores:
        fd = _lock(core)
        if fd is None:
            for taken in fds.values():
                os.close(taken)
            return False
        fds[core] = fd
    _held.update(fds)
    return True


def release() -> None:
    """Let other runs have the cores this process holds."""
    while _held:
        os.close(_held.popitem()[1])
