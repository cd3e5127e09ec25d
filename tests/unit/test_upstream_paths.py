"""Artifact names come from the tracking store: one that would land outside the stage's cache is refused."""

from __future__ import annotations

import pytest

from orchestrator.upstream import StageError, Upstream


@pytest.mark.parametrize("path", ["../outside.pt", "checkpoints/../../outside.pt", "/etc/passwd", "", "a\\..\\b"])
def test_an_artifact_path_that_leaves_the_cache_is_refused_before_any_download(tmp_path, path):
    stage = Upstream("expert", "tracker", "run123", "hash", "sqlite:///nowhere.db", tmp_path / "cache", True)
    with pytest.raises(StageError, match=r"stage expert \(tracker, run run123\): artifact path .* is refused"):
        stage.artifact(path)
    assert not (tmp_path / "cache").exists()  # nothing was created or fetched


def test_a_plain_artifact_path_is_read_from_the_runs_own_cache(tmp_path):
    stage = Upstream("expert", "tracker", "run123", "hash", "sqlite:///nowhere.db", tmp_path, True)
    (tmp_path / "run123" / "checkpoints").mkdir(parents=True)
    (tmp_path / "run123" / "checkpoints" / "ckpt-1.pt").write_bytes(b"x")
    assert stage.artifact("checkpoints/ckpt-1.pt") == tmp_path / "run123" / "checkpoints" / "ckpt-1.pt"
