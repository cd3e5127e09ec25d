"""A disk that fills up under a run, and a run directory on a read-only one, on real file systems: a small tmpfs
mounted in a mount namespace of the test's own (`unshare -rm`, as any user may where user namespaces are on).

Full: the file being written is discarded, the run ends FAILED with the reason tagged and one line saying which
file, what stays and how to resume; the checkpoints before stay and the resume, once there is room, continues from
them. Read-only: one line naming run_dir before Hydra or anything else tries to write there."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from orchestrator import checkpoint


def _namespaces() -> bool:
    """Whether this machine lets a process make its own mount namespace (root, or user namespaces on)."""
    try:
        return subprocess.run(["unshare", "-rm", "true"], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not _namespaces(), reason="no private mount namespaces here (unshare -rm refused)"),
]
ROOT = Path(__file__).resolve().parents[2]
RUN = [sys.executable, "-m", "orchestrator", "runtime=local", "scale=smoke", "motion=walk", "progress=false"]
RUN += ["eval.video=false", "algo.loop.checkpoint_every=2"]


# The status and failure tag of the store's one run.
STATUS = """import sys
from mlflow.tracking import MlflowClient
c = MlflowClient(sys.argv[1])
(r,) = c.search_runs([e.experiment_id for e in c.search_experiments()])
print(r.info.status, r.data.tags.get("last_failure", ""), sep="|", end="")
"""


def in_namespace(script: str, cwd: Path) -> subprocess.CompletedProcess:
    """`script` (sh) in a private mount namespace, as root there: its mounts vanish with it."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        ["unshare", "-rm", "sh", "-ec", script], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def test_a_disk_that_fills_up_fails_the_run_in_one_line_and_the_resume_goes_on_from_what_stayed(tmp_path):
    disk, store = tmp_path / "disk", f"sqlite:///{tmp_path / 'mlflow.db'}"
    disk.mkdir()
    run_dir = disk / "run"
    command = shlex.join([*RUN, f"tracking.uri={store}", f"run_dir={run_dir}"])
    first = run_dir / "checkpoints" / "ckpt-0000002.pt"
    script = f"""
mount -t tmpfs -o size=40m tmpfs {disk}
{command} algo.loop.iterations=400 > first.out 2> first.err &
while [ ! -f {first} ] && kill -0 $! 2>/dev/null; do sleep 0.1; done
dd if=/dev/zero of={disk / "fill"} bs=64k 2>/dev/null || true
code=0; wait $! || code=$?
echo "first: $code"
{shlex.join([sys.executable, "-c", STATUS, store])} > status.txt
ls {run_dir / "checkpoints"} > kept.txt
rm {disk / "fill"}
{command} algo.loop.iterations=8 resume=true > second.out 2> second.err
ls {run_dir / "checkpoints"} > after.txt
"""
    proc = in_namespace(script, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "first: 2" in proc.stdout
    err = (tmp_path / "first.err").read_text()
    assert "Traceback" not in err, err[-3000:]
    line = err.strip().splitlines()[-1]
    assert line.startswith(f"error: {run_dir / 'checkpoints'}/") and ": No space left on device (the file being" in line
    kept = (tmp_path / "kept.txt").read_text().split()
    assert not [k for k in kept if k.endswith(".tmp")], kept  # what was being written went
    last = max(k for k in kept if k.startswith("ckpt-") and k.endswith(".pt"))
    assert f"{last} stays, the last complete checkpoint); the run is FAILED: free space, then resume with " in line
    status_then, tag_then = (tmp_path / "status.txt").read_text().split("|")
    assert status_then == "FAILED" and "No space left on device" in tag_then
    client = MlflowClient(store)
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    assert len(runs) == 1 and runs[0].info.status == "FINISHED"  # the resume went on in the same MLflow run
    second = (tmp_path / "second.err").read_text()
    assert f"resumed from {run_dir / 'checkpoints' / last} at iteration {int(last[5:12])}" in second, second[-3000:]
    assert "ckpt-0000008.pt" in (tmp_path / "after.txt").read_text().split()
    assert checkpoint.latest(run_dir / "checkpoints") is None  # the tmpfs went with the namespace


def test_a_run_dir_on_a_read_only_disk_is_refused_in_one_line_before_anything_writes(tmp_path):
    disk = tmp_path / "disk"
    disk.mkdir()
    command = shlex.join([*RUN, "tracking=off", f"run_dir={disk / 'run'}"])
    proc = in_namespace(f"mount -t tmpfs -o size=1m,ro tmpfs {disk}\n{command}", tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == [
        f"error: run_dir={disk / 'run'}: cannot write there (Read-only file system); give a run_dir= you can write to"
    ]
    assert list(tmp_path.iterdir()) == [disk]  # nothing in the working directory either
