"""A local MLflow tracking server in a subprocess, for jobs that write in parallel.

SQLite alone locks under parallel writers, so a parallel sweep points every job at one server
that owns the database: `start_local_server(...)` returns once `/health` answers. With `auth=True`
(the sweep's) it runs MLflow's basic-auth app with a fresh admin password, its users in a private
temporary folder: other users of the machine cannot reach the store through it, and clients give
`server.credentials` as environment variables (MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD).

    with start_local_server("sqlite:///runs/mlflow.db", Path("runs/mlartifacts")) as server:
        tracker = MlflowLogger(server.uri, "ablation_alpha", run_dir=...)
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path


class ServerStartError(RuntimeError):
    """The server exited or did not answer in time; the message ends with its log."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on `host` right now (another process may still take it before it is used)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class LocalServer:
    """A running `mlflow server` subprocess (see `start_local_server`). A context manager that stops it."""

    def __init__(self, process: subprocess.Popen, host: str, port: int, log_path: Path):
        self.process = process
        self.host = host
        self.port = port
        self.log_path = log_path
        self.credentials: dict[str, str] = {}  # with auth: MLFLOW_TRACKING_USERNAME and _PASSWORD for clients
        self.private: Path | None = None  # with auth: the users' database and the app's config, removed at stop

    @property
    def uri(self) -> str:
        """The tracking URI to give clients: `http://host:port`."""
        return f"http://{self.host}:{self.port}"

    def running(self) -> bool:
        return self.process.poll() is None

    def log_tail(self, chars: int = 3000) -> str:
        """The end of the server's combined stdout and stderr."""
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the server and the processes it started (SIGTERM, then SIGKILL after `timeout` s)."""
        if self.process.poll() is not None:
            return
        # The server runs in its own session and starts uvicorn workers: signal the whole group.
        pgid = os.getpgid(self.process.pid)
        os.killpg(pgid, signal.SIGTERM)
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(pgid, signal.SIGKILL)
            self.process.wait()
        try:  # workers that outlived the main process
            os.killpg(pgid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        if self.private is not None:
            shutil.rmtree(self.private, ignore_errors=True)

    def __enter__(self) -> LocalServer:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"LocalServer({self.uri}, pid={self.process.pid}, log={self.log_path})"


def start_local_server(
    backend_uri: str,
    artifact_root: Path,
    host: str = "127.0.0.1",
    port: int = 0,
    workers: int = 1,
    timeout: float = 60.0,
    log_path: Path | None = None,
    auth: bool = False,
) -> LocalServer:
    """Start `mlflow server` on `host:port` and wait until it answers `/health`.

    Args:
        backend_uri: the server's store, e.g. `sqlite:///runs/mlflow.db`.
        artifact_root: directory the server stores uploaded artifacts in (it proxies uploads, so
            clients need no access to it).
        host: interface to bind; 127.0.0.1 keeps the server private to this machine.
        port: 0 picks a free port.
        workers: server worker processes; one keeps a SQLite store to a single writer process.
        timeout: seconds to wait for `/health` before giving up.
        log_path: where the server's output goes; default a temporary file.
        auth: run MLflow's basic-auth app; clients need `server.credentials` in their environment.

    Raises:
        ServerStartError: the server exited, or did not answer within `timeout`; the message
            includes the end of its log.
    """
    port = port or free_port(host)
    artifact_root = Path(artifact_root).resolve()
    artifact_root.mkdir(parents=True, exist_ok=True)
    if log_path is None:
        fd, name = tempfile.mkstemp(prefix=f"mlflow-server-{port}-", suffix=".log")
        os.close(fd)
        log_path = Path(name)
    command = [
        sys.executable, "-m", "mlflow", "server",
        "--backend-store-uri", backend_uri,
        "--artifacts-destination", str(artifact_root),
        "--host", host,
        "--port", str(port),
        "--workers", str(workers),
    ]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_TRACKING_")}
    # The server's background job runner (GenAI features) is not needed here; it adds processes and start time.
    env.setdefault("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")
    private, credentials = None, {}
    if auth:
        from orchestrator.tracking import mlflow_auth
        from orchestrator.tracking.secret_files import new_password

        mlflow_auth.require_auth_app()
        private = Path(tempfile.mkdtemp(prefix="mlflow-auth-"))  # 0700
        password = new_password()
        mlflow_auth.write_config(private / "auth.ini", f"sqlite:///{private / 'users.db'}")
        env.update(mlflow_auth.server_env(private / "auth.ini", password))
        command[4:4] = ["--app-name", "basic-auth"]
        credentials = {"MLFLOW_TRACKING_USERNAME": mlflow_auth.ADMIN_USER, "MLFLOW_TRACKING_PASSWORD": password}
    with open(log_path, "ab") as log_file:
        # Its own session, so that stop() can signal the server and the workers it starts as one group.
        process = subprocess.Popen(
            command,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,
            # Linux ties this to the starting thread, not its process: only the main thread's server outlives none.
            preexec_fn=_die_with_parent if threading.current_thread() is threading.main_thread() else None,
        )
    server = LocalServer(process, host, port, Path(log_path))
    server.credentials, server.private = credentials, private
    try:
        _wait_healthy(server, timeout)
    except BaseException:
        server.stop()
        raise
    return server


def _die_with_parent() -> None:
    """In the server's process before it runs: on Linux, SIGTERM it when the process that started it dies, even by
    SIGKILL (a sweep killed outright would otherwise leave its server holding the store); elsewhere nothing."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _wait_healthy(server: LocalServer, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        if not server.running():
            raise ServerStartError(
                f"mlflow server on {server.uri} exited with code {server.process.returncode}; "
                f"its log ({server.log_path}) ends:\n{server.log_tail()}"
            )
        try:
            with urllib.request.urlopen(f"{server.uri}/health", timeout=2) as response:
                if response.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        if time.monotonic() > deadline:
            raise ServerStartError(
                f"mlflow server on {server.uri} did not answer /health within {timeout:.0f} s; "
                f"its log ({server.log_path}) ends:\n{server.log_tail()}"
            )
        time.sleep(0.1)
