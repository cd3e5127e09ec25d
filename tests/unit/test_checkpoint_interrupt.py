"""What an interrupted run says, and the trainer-side fallback of a resume (a method with upstream stages,
whose checkpoints are checked only as the trainer restores them)."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from orchestrator import build, checkpoint
from orchestrator.__main__ import _interrupted_line


def test_the_interrupt_line_names_the_iteration_the_checkpoint_and_the_resume_command(tmp_path):
    run_dir = tmp_path / "my run"
    checkpoint.save(run_dir / "checkpoints", 6, {"w": 1})
    cfg = SimpleNamespace(run_dir=str(run_dir))
    line = _interrupted_line(cfg, build.Interrupted(7, run_dir))
    # Outside a Hydra app there are no overrides to repeat; the directory is quoted for the shell.
    assert line == (
        f"interrupted at iteration 7 (a resume starts from ckpt-0000006.pt); "
        f"resume with: python -m orchestrator 'run_dir={run_dir}' resume=true"
    )


def test_an_interrupted_stage_names_its_own_checkpoint(tmp_path):
    stage = tmp_path / "run" / "stages" / "tracker-0123abcd"
    checkpoint.save(stage / "checkpoints", 40, {"w": 1})
    line = _interrupted_line(SimpleNamespace(run_dir=str(tmp_path / "run")), build.Interrupted(41, stage))
    assert line.startswith(f"interrupted at iteration 41 (a resume starts the stage in {stage} from ckpt-0000040.pt)")


def test_an_interrupt_before_training_says_a_resume_starts_over(tmp_path):
    line = _interrupted_line(SimpleNamespace(run_dir=str(tmp_path)), KeyboardInterrupt())
    assert line.startswith("interrupted before training started (a resume starts from scratch: no checkpoint yet)")


class Restorer:
    """A trainer whose `restore` refuses the checkpoints named in `bad`, as Trainer.restore does."""

    def __init__(self, bad: set[str]):
        self.bad, self.tried = bad, []

    def restore(self, path: Path) -> None:
        self.tried.append(path.name)
        if path.name in self.bad:
            raise checkpoint.CheckpointError(path, "world_model: size mismatch for net.0.weight")


def test_restore_falls_back_to_the_newest_older_checkpoint_that_fits(tmp_path, capsys):
    paths = [checkpoint.save(tmp_path, i, {"w": i}) for i in (2, 4, 6)]
    trainer = Restorer({"ckpt-0000004.pt"})
    # Preflight already passed over ckpt-6 (say): the trainer starts at ckpt-4 and goes on to ckpt-2.
    assert build._restore(trainer, paths[1]) == paths[0]
    assert trainer.tried == ["ckpt-0000004.pt", "ckpt-0000002.pt"]
    assert (
        capsys.readouterr().err
        == f"resume: skipping checkpoint {paths[1]}: world_model: size mismatch for net.0.weight\n"
    )


def test_restore_raises_when_no_checkpoint_fits(tmp_path):
    paths = [checkpoint.save(tmp_path, i, {"w": i}) for i in (2, 4)]
    with pytest.raises(checkpoint.CheckpointError, match="ckpt-0000002.pt: world_model"):
        build._restore(Restorer({"ckpt-0000002.pt", "ckpt-0000004.pt"}), paths[1])


def test_a_second_ctrl_c_while_an_interrupted_run_closes_is_ignored():
    before = signal.getsignal(signal.SIGINT)  # Python's own (tests/conftest.py sees to it)
    with build._shielded(True):
        signal.raise_signal(signal.SIGINT)  # to this (the main) thread, before it returns: ignored
        time.sleep(0.05)
    assert signal.getsignal(signal.SIGINT) is before
    with pytest.raises(KeyboardInterrupt), build._shielded(False):  # a run that was not interrupted: as ever
        signal.raise_signal(signal.SIGINT)
        time.sleep(0.05)
