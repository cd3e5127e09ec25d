"""Checkpoint files: durable and atomic saves, an interrupted save that leaves nothing behind, keeping the
newest K, and the run directory's lock."""

from __future__ import annotations

import hashlib
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from orchestrator import checkpoint
from orchestrator.schema import ConfigError, LoopConfig


def state(i: int) -> dict:
    return {"loop": {"iteration": i}, "net": {"w": torch.full((4,), float(i))}}


def test_a_save_fsyncs_the_file_then_its_directory(tmp_path, monkeypatch):
    synced = []
    real = os.fsync

    def fsync(fd: int) -> None:
        mode = os.fstat(fd).st_mode
        synced.append("dir" if stat.S_ISDIR(mode) else "file" if stat.S_ISREG(mode) else "other")
        real(fd)

    monkeypatch.setattr(checkpoint.os, "fsync", fsync)
    path = checkpoint.save(tmp_path, 7, state(7))
    # The file's bytes before the rename, the directory's entry after it.
    assert synced == ["file", "dir"]
    assert path.name == "ckpt-0000007.pt" and torch.equal(checkpoint.load(path)["net"]["w"], torch.full((4,), 7.0))


def test_an_interrupted_save_leaves_no_tmp_and_the_older_checkpoints_as_they_were(tmp_path, monkeypatch):
    first = checkpoint.save(tmp_path, 2, state(2))
    before = first.read_bytes()

    def cut_short(obj, f):  # Ctrl-C halfway through writing the archive
        f.write(b"PK\x03\x04" + b"\0" * 1000)
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint.torch, "save", cut_short)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.save(tmp_path, 4, state(4))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt-0000002.pt", "ckpt-0000002.pt.sha256"]
    assert first.read_bytes() == before


def test_newest_first_orders_by_iteration(tmp_path):
    for i in (10, 2, 100):
        checkpoint.save(tmp_path, i, state(i))
    (tmp_path / "notes.txt").write_text("not a checkpoint")
    assert [p.name for p in checkpoint.newest_first(tmp_path)] == [
        "ckpt-0000100.pt",
        "ckpt-0000010.pt",
        "ckpt-0000002.pt",
    ]
    assert checkpoint.latest(tmp_path).name == "ckpt-0000100.pt"
    assert checkpoint.latest(tmp_path / "none") is None


def test_prune_keeps_the_newest_k_and_removes_stray_tmp_files(tmp_path):
    for i in range(1, 6):
        checkpoint.save(tmp_path, i, state(i))
    (tmp_path / "ckpt-0000006.tmp").write_bytes(b"PK\x03\x04 left by a crash")
    removed = checkpoint.prune(tmp_path, keep=2)
    assert [p.name for p in removed] == ["ckpt-0000003.pt", "ckpt-0000002.pt", "ckpt-0000001.pt"]
    kept = ["ckpt-0000004.pt", "ckpt-0000004.pt.sha256", "ckpt-0000005.pt", "ckpt-0000005.pt.sha256"]
    assert sorted(p.name for p in tmp_path.iterdir()) == kept  # each digest goes with its checkpoint
    assert checkpoint.prune(tmp_path, keep=2) == []


def test_prune_forgets_a_checkpoint_before_deleting_it_so_a_cut_short_prune_is_redone(tmp_path):
    for i in range(1, 4):
        checkpoint.save(tmp_path, i, state(i))
    seen = []

    def forget(path):  # the store's copy first; Ctrl-C before the file here goes
        seen.append((path.name, path.exists()))
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        checkpoint.prune(tmp_path, keep=1, forget=forget)
    assert seen == [("ckpt-0000002.pt", True)]
    assert len(list(tmp_path.glob("ckpt-*.pt"))) == 3  # still here: the next prune forgets it again
    forgotten = []
    checkpoint.prune(tmp_path, keep=1, forget=lambda p: forgotten.append(p.name))
    assert forgotten == ["ckpt-0000002.pt", "ckpt-0000001.pt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt-0000003.pt", "ckpt-0000003.pt.sha256"]


def test_prune_keeps_the_replay_buffers_of_the_newest_only_and_drops_those_without_their_checkpoint(tmp_path):
    for i in range(1, 4):
        checkpoint.save(tmp_path, i, {"replay": {"size": i}}, stem=checkpoint.REPLAY_STEM)
        checkpoint.save(tmp_path, i, state(i))
    checkpoint.save(tmp_path, 4, {"replay": {"size": 4}}, stem="replay")  # a crash before ckpt-4 was written
    (tmp_path / "replay-0000005.tmp").write_bytes(b"PK\x03\x04 left by a crash")
    assert checkpoint.replay_path(tmp_path / "ckpt-0000003.pt") == tmp_path / "replay-0000003.pt"
    checkpoint.prune(tmp_path, keep=2, replay_keep=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "ckpt-0000002.pt", "ckpt-0000002.pt.sha256", "ckpt-0000003.pt", "ckpt-0000003.pt.sha256",
        "replay-0000003.pt", "replay-0000003.pt.sha256",
    ]  # fmt: skip
    assert checkpoint.load(tmp_path / "replay-0000003.pt") == {"replay": {"size": 3}}
    checkpoint.prune(tmp_path, keep=2, replay_keep=0)
    assert not list(tmp_path.glob("replay-*"))


def test_checkpoint_keep_below_one_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match=r"algo\.loop\.checkpoint_keep must be at least 1, got 0"):
        LoopConfig(checkpoint_keep=0)
    assert LoopConfig().checkpoint_keep == 3


def test_a_second_lock_on_a_run_directory_is_refused_naming_it(tmp_path):
    with checkpoint.lock_run_dir(tmp_path):
        with pytest.raises(checkpoint.RunDirBusy, match=f"run_dir={tmp_path}: another command is running"):
            checkpoint.lock_run_dir(tmp_path)
        # Another process too (flock: the lock is the open file's, whoever asks).
        code = (
            "import sys\nfrom orchestrator import checkpoint\n"
            "try:\n    checkpoint.lock_run_dir(sys.argv[1])\nexcept checkpoint.RunDirBusy:\n    sys.exit(3)\n"
        )
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
        assert subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env).returncode == 3
    with checkpoint.lock_run_dir(tmp_path):  # released when the run ends
        pass


def test_the_default_run_directory_is_named_to_the_microsecond():
    """Two commands started in the same second get run directories of their own (were they to meet, the
    second would find it locked)."""
    from hydra import compose, initialize_config_dir

    from orchestrator.compose import register

    register()
    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("config", return_hydra_config=True)
    run_dir, sweep_dir = cfg.hydra.run.dir, cfg.hydra.sweep.dir
    assert re.fullmatch(r"outputs/default/\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d-\d{6}", run_dir), run_dir
    assert sweep_dir == run_dir


def test_a_checkpoint_changed_after_its_save_is_refused_by_its_digest(tmp_path):
    path = checkpoint.save(tmp_path, 1, state(1))
    line = checkpoint.digest_path(path).read_text()
    assert line == f"{hashlib.sha256(path.read_bytes()).hexdigest()}  ckpt-0000001.pt\n"  # sha256sum's format
    assert checkpoint.load(path)["loop"]["iteration"] == 1
    other = tmp_path / "other"
    torch.save(checkpoint.load(checkpoint.save(other, 1, state(7))), path)  # a valid archive, other tensors
    with pytest.raises(checkpoint.CheckpointError, match=r"corrupt: its contents do not match the SHA-256 in"):
        checkpoint.load(path)
    checkpoint.digest_path(path).unlink()  # a checkpoint from before digests loads unchecked
    assert checkpoint.load(path)["loop"]["iteration"] == 7


def test_ctrl_c_in_the_middle_of_a_write_is_a_keyboard_interrupt_and_leaves_no_tmp(tmp_path, monkeypatch):
    """torch's zip writer turned a KeyboardInterrupt raised by a write into `RuntimeError: unexpected pos`, and
    the run ended with a traceback instead of KILLED with the command that resumes it."""
    real_open = open

    class Interrupting:
        def __init__(self, f):
            self.f, self.calls = f, 0

        def write(self, data):
            self.calls += 1
            if self.calls == 3:
                raise KeyboardInterrupt
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.f.__exit__(*exc)

    checkpoint.save(tmp_path, 1, state(1))
    monkeypatch.setattr(checkpoint, "open", lambda *a, **k: Interrupting(real_open(*a, **k)), raising=False)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.save(tmp_path, 2, {"x": torch.zeros(100_000)})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt-0000001.pt", "ckpt-0000001.pt.sha256"]
