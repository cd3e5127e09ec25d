"""Processes of `orchestrator.cluster`: started in their own session, waited for, and stopped by that session.

Every long-lived service (`ray start --block`, `mlflow server`) is started as the leader of a new
session. Its record (`pid`, `created`) is what `down` needs to stop exactly what `up` started: the
leader gets SIGTERM, then every process still in that session (Ray's workers, uvicorn's workers)
gets SIGTERM and, after a grace period, SIGKILL. The creation time guards against a reused pid.
Nothing here looks processes up by name.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil

from orchestrator.errors import ServiceError


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on `host` now (another process may take it before it is bound)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def free_ports(n: int, host: str = "127.0.0.1") -> list[int]:
    """`n` distinct free ports (held open together while choosing, so none is picked twice)."""
    sockets = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind((host, 0))
            sockets.append(s)
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def start_session(command: list[str], log_path: Path, env: dict[str, str]) -> dict[str, Any]:
    """Start `command` as the leader of a new session, output appended to `log_path`; its record."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "ab") as log:
        process = subprocess.Popen(
            command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, start_new_session=True
        )
    try:
        created = psutil.Process(process.pid).create_time()
    except psutil.NoSuchProcess:
        created = time.time()
    return {"pid": process.pid, "created": created, "log": str(log_path)}


def _leader(record: dict[str, Any]) -> psutil.Process | None:
    """The recorded leader if it still runs and is the same process (not a reused pid)."""
    try:
        proc = psutil.Process(record["pid"])
        if abs(proc.create_time() - record["created"]) < 1.0 and proc.status() != psutil.STATUS_ZOMBIE:
            return proc
    except (psutil.NoSuchProcess, psutil.AccessDenied, KeyError):
        pass
    return None


def alive(record: dict[str, Any] | None) -> bool:
    return record is not None and _leader(record) is not None


def session_members(record: dict[str, Any]) -> list[psutil.Process]:
    """Processes in the recorded leader's session started after it (the leader included, while it runs)."""
    members = []
    for proc in psutil.process_iter(["pid", "create_time"]):
        try:
            if os.getsid(proc.pid) == record["pid"] and proc.info["create_time"] >= record["created"] - 1.0:
                members.append(proc)
        except (ProcessLookupError, PermissionError, psutil.Error):
            continue
    return members


def stop_session(record: dict[str, Any], grace_s: float = 20.0) -> None:
    """SIGTERM the leader and wait; then SIGTERM, and after 5 s SIGKILL, whatever is left of its session."""
    leader = _leader(record)
    if leader is not None:
        try:
            leader.send_signal(signal.SIGTERM)
            leader.wait(grace_s)
        except psutil.TimeoutExpired:
            pass
        except psutil.NoSuchProcess:
            pass
    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        members = session_members(record)
        if not members:
            return
        for proc in members:
            try:
                proc.send_signal(sig)
            except psutil.NoSuchProcess:
                pass
        psutil.wait_procs(members, timeout=wait_s)


def http_json(url: str, token: str | None = None, timeout: float = 3.0) -> Any:
    """GET `url` (with a bearer token if given) and decode its JSON body."""
    request = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    with urllib.request.urlopen(request, timeout=timeout) as response:
        return json.loads(response.read().decode() or "null")


def http_ok(url: str, timeout: float = 3.0) -> bool:
    """Whether GET `url` answers 200."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.status == 200
    except (OSError, urllib.error.URLError):
        return False


def wait_until(
    what: str,
    check: Callable[[], bool],
    timeout_s: float,
    log: str | Path,
    record: dict[str, Any] | None = None,
    retry_on: tuple[type[BaseException], ...] = (),
) -> None:
    """Poll `check` until it is true; raise a one-line ServiceError naming `what` and `log` when the recorded
    process exits or `timeout_s` passes. Connection errors (and `retry_on`) raised by `check` count as 'not yet'."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if check():
                return
        except (OSError, urllib.error.URLError, ValueError, ConnectionError, *retry_on):
            pass
        if record is not None and not alive(record):
            raise ServiceError(f"{what} exited during start-up; see its log {log}")
        if time.monotonic() > deadline:
            raise ServiceError(f"{what} did not come up within {timeout_s:.0f} s; see its log {log}")
        time.sleep(0.5)
