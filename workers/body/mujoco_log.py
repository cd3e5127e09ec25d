"""MuJoCo's warnings into Python logging, not into MUJOCO_LOG.TXT in the user's working directory.

MuJoCo's default warning handler prints a warning and appends it to MUJOCO_LOG.TXT in the working
directory (an unstable simulation: "Nan, Inf or huge value in QACC at DOF 0"). `route_warnings`
replaces it, for the whole process, with one that logs to this module's logger: the first few as
warnings, the rest (one per environment that blows up) at debug level. The simulator counts the
warnings per environment as well (`workers.sim.env.BatchedSim.warning_counts`). `workers.body` calls it
on import, so every process that simulates routes its own. The handler runs on mujoco.batch's threads
too, which is safe: the bindings take the GIL to call it.
"""

from __future__ import annotations

import logging

import mujoco

log = logging.getLogger(__name__)

SHOWN = 5  # warnings logged at warning level in a process; the rest at debug level
_seen = 0


def _warning(message: str) -> None:
    global _seen
    _seen += 1
    log.log(logging.WARNING if _seen <= SHOWN else logging.DEBUG, "MuJoCo: %s", message.strip())
    if _seen == SHOWN:
        log.warning("further MuJoCo warnings are logged at debug level (logger %s)", __name__)


def route_warnings() -> None:
    mujoco.set_mju_user_warning(_warning)
