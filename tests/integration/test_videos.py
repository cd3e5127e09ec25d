"""Evaluation videos in whole runs: MP4s logged to the run's MLflow artifacts, readable and of the size asked.

Whole smoke runs take a minute or more on a busy two-core machine, hence `slow`; tests/unit/test_render.py
covers the same code in seconds.
"""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import pytest
from mlflow.tracking import MlflowClient

from orchestrator.build import run

# Short, small videos: the test is about the plumbing, not the picture (tests/unit/test_render.py).
VIDEO = (
    "eval.video=true",
    "eval.video_rollouts=2",
    "eval.video_seconds=1",
    "eval.video_width=160",
    "eval.video_height=96",
)


def logged_videos(cfg, tmp_path: Path) -> dict[str, Path]:
    """{artifact path: downloaded file} of every MP4 under the run's videos/."""
    client = MlflowClient(f"sqlite:///{cfg.run_dir}/mlflow.db")
    run_id = json.loads((Path(cfg.run_dir) / "run.json").read_text())["run_id"]
    out = {}
    for folder in client.list_artifacts(run_id, "videos"):
        assert folder.is_dir, folder.path
        for a in client.list_artifacts(run_id, folder.path):
            if a.path.endswith(".mp4"):
                assert a.file_size > 0
                out[a.path] = Path(client.download_artifacts(run_id, a.path, str(tmp_path)))
    return out


@pytest.mark.slow
def test_controlvae_smoke_run_logs_its_evaluation_videos(smoke, tmp_path):
    cfg = smoke(*VIDEO)
    run(cfg)
    videos = logged_videos(cfg, tmp_path / "download")
    final = {p for p in videos if p.startswith("videos/final/")}
    assert final == {"videos/final/fall-0.mp4", "videos/final/fall-1.mp4", "videos/final/tracking-humanoid3d_walk.mp4"}
    frames = iio.imread(videos["videos/final/tracking-humanoid3d_walk.mp4"])
    assert frames.shape == (31, 96, 160, 3)  # the start and one frame per control step for 1 s at 30 Hz
    fall = iio.imread(videos["videos/final/fall-0.mp4"])
    assert 2 <= len(fall) <= 31 and fall.shape[1:] == (96, 160, 3)


@pytest.mark.slow
def test_video_false_logs_no_video(smoke, tmp_path):
    cfg = smoke("eval.video=false", "algo.loop.iterations=2", "algo.loop.checkpoint_every=0")
    run(cfg)
    assert logged_videos(cfg, tmp_path / "download") == {}


@pytest.mark.slow
def test_amp_smoke_run_logs_a_policy_video(smoke, tmp_path):
    cfg = smoke("algo=amp", *VIDEO)
    run(cfg)
    videos = logged_videos(cfg, tmp_path / "download")
    final = [p for p in videos if p.startswith("videos/final/")]
    assert len(final) == 1 and final[0].startswith("videos/final/policy-humanoid3d_walk")
    frames = iio.imread(videos[final[0]])
    assert 2 <= len(frames) <= 31 and frames.shape[1:] == (96, 160, 3)
