"""No password of a tracking URI in anything the command prints or writes when it stops: a refusal before
anything starts, Ctrl-C's resume line, an unexpected exception (Hydra's own log line and the traceback), and
Hydra's record of the run (`.hydra/*.yaml`). The command runs for real (`python -m orchestrator`'s entry
point); where a path needs a failure in the middle of a run, `orchestrator.build.run` is replaced by one that
fails that way, since nothing else makes a run fail there on demand."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.tracking.server import free_port

ROOT = Path(__file__).resolve().parents[2]
PASSWORD = "Wz4Tq9vB"  # noqa: S105 - a test secret, looked for in every output

SCRIPT = """
import sys
import orchestrator.build

def fails(*args, **kwargs):
    if {how!r} == "interrupt":
        raise KeyboardInterrupt
    raise RuntimeError("could not reach " + {uri!r})

orchestrator.build.run = fails
import runpy
sys.argv = ["orchestrator", *{overrides!r}]
runpy.run_module("orchestrator", run_name="__main__", alter_sys=True)  # as python -m orchestrator runs it
"""


def invoke(tmp_path: Path, how: str, *extra: str) -> tuple[subprocess.CompletedProcess, Path]:
    uri = f"http://carol:{PASSWORD}@127.0.0.1:{free_port()}"
    hydra_dir = tmp_path / "hydra"
    overrides = [
        "scale=smoke",
        "motion=walk",
        f"tracking.uri={uri}",
        f"run_dir={tmp_path / 'run'}",
        f"hydra.run.dir={hydra_dir}",
        *extra,
    ]
    code = SCRIPT.format(how=how, uri=uri, overrides=overrides)
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    return proc, hydra_dir


def assert_nowhere(proc: subprocess.CompletedProcess, hydra_dir: Path) -> None:
    assert PASSWORD not in proc.stdout and PASSWORD not in proc.stderr, proc.stderr[-2000:]
    written = [p for p in (hydra_dir / ".hydra").glob("*.yaml")]
    assert {p.name for p in written} == {"config.yaml", "hydra.yaml", "overrides.yaml"}
    assert all(PASSWORD not in p.read_text() for p in written)
    assert "carol:***@" in (hydra_dir / ".hydra" / "overrides.yaml").read_text()


@pytest.mark.parametrize(
    "how,extra,code,last",
    [
        ("refused", ("seed=-1",), 2, "config error: seed: -1 is outside 0"),
        ("interrupt", (), 130, "interrupted before training started (a resume starts from scratch"),
        ("unexpected", (), 1, "Set the environment variable HYDRA_FULL_ERROR=1"),
    ],
)
def test_no_password_in_what_a_stopped_command_prints_or_writes(tmp_path, how, extra, code, last):
    proc, hydra_dir = invoke(tmp_path, how, *extra)
    assert proc.returncode == code, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith(last), proc.stderr[-2000:]
    assert_nowhere(proc, hydra_dir)
    if how == "unexpected":  # Hydra's own lines, masked
        assert (
            "Error executing job with overrides: ['scale=smoke', 'motion=walk', 'tracking.uri=http://carol:***@"
            in proc.stderr
        )
        assert "RuntimeError: could not reach http://carol:***@127.0.0.1:" in proc.stderr
    if how == "interrupt":  # the resume command masks it and says where it goes instead
        assert "resume with: MLFLOW_TRACKING_PASSWORD=... python -m orchestrator" in proc.stderr
        assert "tracking.uri=http://carol:***@127.0.0.1:" in proc.stderr
