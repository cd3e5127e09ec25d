"""Checkpoints over real smoke runs: a truncated newest checkpoint resumes from the one before (its replay buffer
refilled: only the newest keeps one beside it), only the newest `algo.loop.checkpoint_keep` stay here and the newest
`tracking.store_checkpoints` in the MLflow store, a second command on a busy run directory is refused, and Ctrl-C
ends a run KILLED with the one command that resumes it."""

from __future__ import annotations

import json
import logging
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from orchestrator import checkpoint, preflight
from orchestrator.build import run

ROOT = Path(__file__).resolve().parents[2]


def names(directory: Path) -> list[str]:
    """The checkpoints in `directory`, after checking that each has its digest beside it and nothing else is there."""
    files = sorted(p.name for p in directory.iterdir())
    ckpts = [n for n in files if n.endswith(".pt")]
    assert files == sorted([*ckpts, *(f"{n}.sha256" for n in ckpts)]), files
    return ckpts


def stored(run_dir: Path, run_id: str) -> list[str]:
    """The checkpoints in the run's store, after checking that each has its digest beside it there too."""
    client = MlflowClient(f"sqlite:///{run_dir}/mlflow.db")
    files = sorted(Path(a.path).name for a in client.list_artifacts(run_id, "checkpoints"))
    ckpts = [n for n in files if n.endswith(".pt")]
    assert files == sorted([*ckpts, *(f"{n}.sha256" for n in ckpts)]), files
    return ckpts


@pytest.mark.slow
def test_a_truncated_newest_checkpoint_resumes_from_the_one_before(smoke, capsys, caplog):
    common = ("algo.loop.checkpoint_every=2", "algo.loop.checkpoint_keep=2", "tracking.log_model=false")
    first = smoke("algo.loop.iterations=4", *common, name="r")
    run(first)
    run_dir = Path(first.run_dir)
    ckpts = run_dir / "checkpoints"
    assert names(ckpts) == ["ckpt-0000002.pt", "ckpt-0000004.pt", "replay-0000004.pt"]
    assert "replay" not in checkpoint.load(ckpts / "ckpt-0000004.pt")  # beside it, not in it
    assert checkpoint.load(ckpts / "replay-0000004.pt")["replay"]["size"] > 0
    newest = ckpts / "ckpt-0000004.pt"
    newest.write_bytes(newest.read_bytes()[: newest.stat().st_size // 2])  # a disk that filled up, say
    run_id = json.loads((run_dir / "run.json").read_text())["run_id"]

    # Had the one before it been spoiled too (in a copy): refused, naming the newest and saying so.
    spoiled = smoke("algo.loop.iterations=6", *common, "resume=true", name="spoiled")
    shutil.copytree(ckpts, Path(spoiled.run_dir) / "checkpoints")
    (Path(spoiled.run_dir) / "checkpoints" / "ckpt-0000002.pt").write_text("step,reward\n1,0.5\n")
    with pytest.raises(preflight.InputError) as refused:
        preflight.resume_checkpoint(spoiled, preflight.character_and_clips(spoiled))
    message = str(refused.value)
    assert message.startswith(f"checkpoint {spoiled.run_dir}/checkpoints/ckpt-0000004.pt: truncated or corrupt")
    assert message.endswith("(and the 1 before it do not load either; resume=true; the files are left as they are)")
    capsys.readouterr()

    with caplog.at_level(logging.WARNING, logger="orchestrator.trainer"):
        run(smoke("algo.loop.iterations=6", *common, "resume=true", name="r"))
    err = capsys.readouterr().err
    assert "resume: ckpt-0000002.pt has no replay buffer beside it" in caplog.text  # it refills
    assert f"resume: skipping checkpoint {newest}: truncated or corrupt" in err
    assert f"resumed from {ckpts / 'ckpt-0000002.pt'} at iteration 2" in err
    # Iterations 3 to 6 again, into the same MLflow run; the truncated file was written anew at iteration 4,
    # and only the newest two stay here, the newest in the store.
    client = MlflowClient(f"sqlite:///{run_dir}/mlflow.db")
    assert json.loads((run_dir / "run.json").read_text())["run_id"] == run_id
    assert client.get_run(run_id).info.status == "FINISHED"
    per_iteration = 2 * 8 * 16  # workers x environments x steps
    steps = [m.step for m in client.get_metric_history(run_id, "throughput/samples_per_s")]
    assert steps == [per_iteration * i for i in (1, 2, 3, 4, 3, 4, 5, 6)]
    assert names(ckpts) == ["ckpt-0000004.pt", "ckpt-0000006.pt", "replay-0000006.pt"]
    assert checkpoint.load(newest)["loop"]["iteration"] == 4
    assert stored(run_dir, run_id) == ["ckpt-0000006.pt"]


def orchestrator(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "orchestrator", *args],
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.slow
def test_ctrl_c_marks_the_run_killed_and_prints_the_command_that_resumes_it(tmp_path):
    run_dir = tmp_path / "run"
    args = [
        "runtime=local",
        "scale=smoke",
        "motion=walk",
        "eval.video=false",
        "tracking.log_model=false",
        "progress=false",
        "algo.loop.checkpoint_every=2",
        "algo.loop.iterations=1000",
    ]
    hydra = f"hydra.run.dir={tmp_path / 'hydra'}"  # Hydra's own record: not in the repository's outputs/
    proc = orchestrator(*args, hydra, f"run_dir={run_dir}")
    ckpts = run_dir / "checkpoints"
    deadline = time.time() + 300
    while time.time() < deadline and not (ckpts / "ckpt-0000004.pt").exists():
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        time.sleep(0.2)
    run_file = (run_dir / "run.json").read_text()

    # A second command on the same run directory: one line naming it, exit status 2, nothing written.
    second = orchestrator(*args, hydra, f"run_dir={run_dir}")
    _, err = second.communicate(timeout=300)
    assert second.returncode == 2, err[-2000:]
    assert err.strip().splitlines() == [
        f"error: run_dir={run_dir}: another command is running in this directory (it holds run.lock); "
        "wait for it to end, or give another run_dir"
    ]
    assert (run_dir / "run.json").read_text() == run_file

    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    last = err.strip().splitlines()[-1]
    m = re.fullmatch(r"interrupted at iteration (\d+) \(a resume starts from (ckpt-\d+\.pt)\); resume with: (.*)", last)
    assert m, last
    # The overrides as given, Hydra's own (hydra.*) aside.
    command = shlex.join(["python", "-m", "orchestrator", *args, f"run_dir={run_dir}", "resume=true"])
    assert m.group(3) == command
    assert m.group(2) == checkpoint.latest(ckpts).name and int(m.group(1)) >= 4
    assert not list(ckpts.glob("*.tmp"))
    run_id = json.loads((run_dir / "run.json").read_text())["run_id"]
    client = MlflowClient(f"sqlite:///{run_dir}/mlflow.db")
    assert client.get_run(run_id).info.status == "KILLED"

    # The command printed resumes the run (here with a budget that ends it soon).
    resumed_at = int(m.group(2)[5:12])
    resume = shlex.split(m.group(3))[3:]
    resume = [f"algo.loop.iterations={resumed_at + 2}" if a.startswith("algo.loop.iterations=") else a for a in resume]
    again = orchestrator(*resume, hydra)
    _, err = again.communicate(timeout=300)
    assert again.returncode == 0, err[-3000:]
    assert f"resumed from {ckpts / m.group(2)} at iteration {resumed_at}" in err
    assert client.get_run(run_id).info.status == "FINISHED"
    assert len(list(ckpts.glob("ckpt-*.pt"))) <= 3  # algo.loop.checkpoint_keep's default


@pytest.mark.slow
@pytest.mark.parametrize("runtime", ["local", pytest.param("ray", marks=pytest.mark.ray)])
def test_sigterm_stops_a_run_as_ctrl_c_does(tmp_path, runtime):
    """Also on Ray, whose `ray.init` puts in a SIGTERM handler of its own (exit at once: the run FAILED)."""
    run_dir = tmp_path / "run"
    args = [f"runtime={runtime}", "scale=smoke", "motion=walk", "eval.video=false", "tracking=off", "progress=false"]
    args += ["algo.loop.checkpoint_every=1", "algo.loop.iterations=1000", f"hydra.run.dir={tmp_path / 'hydra'}"]
    proc = orchestrator(*args, f"run_dir={run_dir}")
    ckpts = run_dir / "checkpoints"
    try:
        deadline = time.time() + 300
        while time.time() < deadline and not (ckpts / "ckpt-0000002.pt").exists():
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)  # a checkpoint each iteration: often in the middle of one
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err
    assert re.fullmatch(
        r"interrupted at iteration \d+ \(a resume starts from ckpt-\d+\.pt\); resume with: .*",
        err.strip().splitlines()[-1],
    )
    assert not list(ckpts.glob("*.tmp"))
    assert len(list(ckpts.glob("ckpt-*.pt"))) <= 3
    checkpoint.load(checkpoint.latest(ckpts))  # complete
