"""The tracker deletes, after upload, only the folders it made for its own files, whatever a spool line says."""

from __future__ import annotations

from orchestrator.tracking.spool import ARTIFACT_DIR, _discard_owned


def record(path) -> dict:
    return {"op": "artifact", "run": "r", "path": str(path), "artifact_path": None, "owned": True}


def test_only_a_folder_the_tracker_made_under_the_run_directory_is_deleted(tmp_path):
    root = tmp_path / "run" / ARTIFACT_DIR
    mine = root / "0123abcd"
    mine.mkdir(parents=True)
    (mine / "figure.png").write_bytes(b"png")
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "data.npz").write_bytes(b"data")
    (root / "link").symlink_to(precious, target_is_directory=True)
    crafted = [
        precious / "data.npz",  # a folder elsewhere
        root / "data.npz",  # the root itself
        root / ".." / ".." / "precious" / "data.npz",  # climbing out
        root / "link" / "data.npz",  # a symlink under the root to a folder elsewhere
    ]
    for path in crafted:
        _discard_owned(record(path), root)
        assert (precious / "data.npz").exists() and root.is_dir(), path
    _discard_owned({**record(mine / "figure.png"), "owned": False}, root)  # not owned: kept
    assert mine.exists()
    _discard_owned(record(mine / "figure.png"), root)
    assert not mine.exists() and root.is_dir()
