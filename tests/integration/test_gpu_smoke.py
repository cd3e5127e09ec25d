"""The GPU smoke's dry run (`DRY_RUN=cpu sh scripts/gpu-smoke.sh`): every check runs here on the CPU and Warp's CPU
device, in order, one line each, and passes; the exit status says so."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[2]
CHECKS = ["devices", "rollout", "learners", "compiled", "warp-graph", "tracking-on-warp", "training"]


def test_the_gpu_smokes_dry_run_passes_every_check_on_the_cpu():
    env = {**os.environ, "DRY_RUN": "cpu", "PYTHON": sys.executable}  # this environment, wherever it lives
    smoke = ["sh", "scripts/gpu-smoke.sh"]
    proc = subprocess.run(smoke, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    lines = [line for line in proc.stdout.splitlines() if line.split(" ")[0] in ("PASS", "FAIL", "SKIP")]
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert [line.split(" ")[1] for line in lines] == [*CHECKS, "all"], lines
    assert all(line.startswith("PASS") for line in lines), lines
