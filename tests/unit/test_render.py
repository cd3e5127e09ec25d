"""Evaluation videos: what is recorded, what the MP4s show, and what happens without GL.

Rendering runs in `orchestrator.evaluation.video`'s child process (this process imported MuJoCo without a GL
backend), so the videos are checked as the service writes them: read back from the MP4 files.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from orchestrator.evaluation import video
from orchestrator.evaluation.protocols import evaluate_controller
from orchestrator.schema import Config
from orchestrator.tracking.base import NoOpLogger
from workers.evaluation.controller import fall_start, time_until_fall
from workers.evaluation.imitation import reference_actor
from workers.evaluation.render import (
    FALL_TAIL_S,
    Recording,
    record_fall_rollouts,
    record_policy_episode,
    record_tracking,
)
from workers.learners.base import Weights
from workers.learners.vae import VAEConfig, build_controller

SMALL = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(64,))
HZ = 30
W, H = 240, 160  # not the default size, so that the size is seen to come from the arguments


def write_videos(recordings, out_dir: Path, fps: float, width: int, height: int, run: str | None = None) -> list[Path]:
    """`video.RenderJob` in the foreground: out_dir/<name>.mp4 for every recording ([] without GL)."""
    with video.RenderJob(recordings, fps, width, height, run) as job:
        paths = job.wait()
        if paths:
            out_dir.mkdir(parents=True, exist_ok=True)
        return [Path(shutil.move(p, out_dir / p.name)) for p in paths]


def small_controller(character):
    torch.manual_seed(0)
    return build_controller(character.num_bodies, character.num_actions, SMALL)


class RecordingLogger(NoOpLogger):
    """Keeps every artifact logged: (file name, artifact path, size in bytes)."""

    def __init__(self):
        self.artifacts: list[tuple[str, str | None, int]] = []

    @property
    def run_id(self) -> str:
        return "test-run"

    def log_artifact(self, local_path, artifact_path=None):
        path = Path(local_path)
        self.artifacts.append((path.name, artifact_path, path.stat().st_size))


def small_config(**eval_overrides) -> Config:
    cfg = Config()
    cfg.algo.vae = SMALL
    cfg.progress = False
    cfg.eval = dataclasses.replace(
        cfg.eval,
        fall_rollouts=2,
        fall_max_seconds=1.0,
        tracking_seconds=0.5,
        random_rollouts=1,
        random_seconds=0.2,
        video_seconds=0.5,
        video_width=64,
        video_height=48,
        **eval_overrides,
    )
    return cfg


@pytest.fixture
def fresh_gl(monkeypatch):
    """A process that has not tried any GL backend yet (the module remembers the outcome)."""
    monkeypatch.setattr(video, "_GL", video._GLState())


# ----------------------------------------------------------------------------
# Recording
# ----------------------------------------------------------------------------
def test_fall_rollouts_end_a_second_after_the_fall(character, walk_run):
    c = small_controller(character)
    recs = record_fall_rollouts(c, character, walk_run, num_rollouts=2, max_seconds=4.0, seed=3)
    # The same start, seed and batch size as time_until_fall: the same rollouts, so the same falls.
    times = time_until_fall(c, character, walk_run, num_rollouts=2, max_seconds=4.0, seed=3)["times"]
    start = walk_run.state(*[np.array([v]) for v in fall_start(walk_run)]).qpos[0]
    for i, (rec, t) in enumerate(zip(recs, times, strict=True)):
        assert rec.name == f"fall-{i}" and rec.ghost_qpos is None and rec.model is not None
        np.testing.assert_allclose(rec.qpos[0], start)
        fall_step = round(t * HZ)  # an untrained controller falls well within 4 s
        assert fall_step < 4 * HZ
        # The start pose, then one pose per step up to a second after the fall.
        assert len(rec.qpos) == min(fall_step + round(FALL_TAIL_S * HZ), 4 * HZ) + 1


def test_tracking_recording_carries_its_reference(character, walk_run):
    rec = record_tracking(small_controller(character), character, walk_run, max_seconds=1.0)
    assert rec.name == "tracking-humanoid3d_walk"
    assert rec.qpos.shape == rec.ghost_qpos.shape == (HZ + 1, character.model.nq)
    clip = walk_run.clip_id("humanoid3d_walk")
    expected = walk_run.state(np.full(HZ + 1, clip), np.arange(HZ + 1)).qpos
    np.testing.assert_allclose(rec.ghost_qpos, expected)
    np.testing.assert_allclose(rec.qpos[0], expected[0])
    assert not np.allclose(rec.qpos[-1], rec.qpos[0])  # the character moved


def test_policy_episode_follows_an_actor_beside_its_reference(character, walk_run):
    rec = record_policy_episode(reference_actor(walk_run), character, walk_run, max_seconds=0.5, seed=1)
    assert rec.name.startswith("policy-humanoid3d_")
    assert rec.qpos.shape == rec.ghost_qpos.shape and 2 <= len(rec.qpos) <= HZ // 2 + 1
    # Driven by the reference's PD targets, the character stays near its reference (root within 0.3 m).
    assert np.abs(rec.qpos[:, :3] - rec.ghost_qpos[:, :3]).max() < 0.3


# ----------------------------------------------------------------------------
# Rendering (one child process renders every video these tests read)
# ----------------------------------------------------------------------------
def hidden(qpos: np.ndarray) -> np.ndarray:
    """The same poses 5 m under the floor: the camera (which keeps its height) sees an empty scene."""
    q = qpos.copy()
    q[:, 2] -= 5.0
    return q


@pytest.fixture(scope="module")
def videos(character, walk_run, tmp_path_factory):
    clip = walk_run.clip_id("humanoid3d_walk")
    walk = walk_run.state(np.full(12, clip), np.arange(12)).qpos
    m = character.model
    recordings = [
        Recording("walk", walk, None, m),
        Recording("empty", hidden(walk), None, m),
        Recording("ghost", walk, walk, m),
        Recording("ghost-hidden", walk, hidden(walk), m),
    ]
    out = tmp_path_factory.mktemp("videos")
    paths = write_videos(recordings, out, HZ, W, H, run="test")
    assert paths == [out / f"{r.name}.mp4" for r in recordings], video._GL.failure
    return {p.stem: iio.imread(p).astype(int) for p in paths}


def test_videos_have_every_frame_at_the_size_asked(videos):
    for frames in videos.values():
        assert frames.shape == (12, H, W, 3)


def test_the_character_is_in_the_picture(videos):
    walk, empty = videos["walk"], videos["empty"]
    assert empty.std() > 1  # the floor's checks: the empty scene is not a blank frame either
    middle = (slice(None), slice(H // 4, 3 * H // 4), slice(W // 3, 2 * W // 3))
    changed = (np.abs(walk - empty).max(-1) > 40)[middle]
    assert changed.mean() > 0.05  # the character covers a good part of the frame's middle
    corners = np.abs(walk - empty)[:, :, : W // 8]
    assert (corners.max(-1) > 40).mean() < 0.01  # and nothing else changed


def test_the_ghost_stands_beside_the_character(videos):
    ghost, alone = videos["ghost"], videos["ghost-hidden"]
    changed = np.abs(ghost - alone).max(-1) > 40  # [T, H, W]
    right, left = changed[:, :, W // 2 :], changed[:, :, : W // 3]
    assert right.mean() > 0.015  # the ghost, to the right of the image's centre
    assert left.mean() < 0.005  # the character on the left is drawn the same with or without it


def test_gl_backends_fall_back_to_the_next_one(fresh_gl, monkeypatch, tmp_path, character, caplog):
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    assert video.backends() == ["egl", "osmesa"]
    # A first backend that fails (the child's `import mujoco` refuses the name), then one that works.
    monkeypatch.setattr(video, "HEADLESS_BACKENDS", ("no-such-backend", "egl"))
    rec = Recording("x", np.tile(character.model.qpos0, (3, 1)), None, character.model)
    with caplog.at_level(logging.WARNING, logger="orchestrator.evaluation.video"):
        assert write_videos([rec], tmp_path, HZ, W, H) == [tmp_path / "x.mp4"]
    assert len(iio.imread(tmp_path / "x.mp4")) == 3
    assert not caplog.records  # a fallback that works is not worth a warning
    # The backend that worked is the only one tried from then on, whatever MUJOCO_GL says.
    assert video.backends() == ["egl"]
    monkeypatch.setenv("MUJOCO_GL", "glx")
    assert video.backends() == ["egl"]


def test_a_job_left_early_stops_its_child_and_deletes_its_files(character):
    rec = Recording("x", np.tile(character.model.qpos0, (300, 1)), None, character.model)
    with pytest.raises(KeyboardInterrupt), video.RenderJob([rec], HZ, W, H) as job:
        raise KeyboardInterrupt
    assert job._proc is None and not job.dir.exists()


def test_a_user_mujoco_gl_is_the_only_backend_tried(fresh_gl, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert video.backends() == ["osmesa"]


# ----------------------------------------------------------------------------
# In the evaluation
# ----------------------------------------------------------------------------
def weights_of(character) -> Weights:
    return Weights(version=3, state=small_controller(character).state_dict())


def test_evaluation_logs_its_videos(character, walk_run):
    tracker = RecordingLogger()
    evaluate_controller(small_config(), character, walk_run, weights_of(character), tracker, 3, final=False)
    videos = {(name, path) for name, path, size in tracker.artifacts if name.endswith(".mp4") and size > 0}
    assert videos == {
        ("fall-0.mp4", "videos/iter-0000003"),
        ("fall-1.mp4", "videos/iter-0000003"),
        ("tracking-humanoid3d_walk.mp4", "videos/iter-0000003"),
    }


def test_video_false_writes_no_video(character, walk_run, monkeypatch):
    def no_child(*args):
        raise AssertionError("no render process may start with eval.video=false")

    monkeypatch.setattr(video.RenderJob, "_start", no_child)
    tracker = RecordingLogger()
    cfg = small_config(video=False)
    metrics = evaluate_controller(cfg, character, walk_run, weights_of(character), tracker, 3, final=True)
    assert "eval/time_until_fall_mean" in metrics
    assert tracker.artifacts and not [a for a in tracker.artifacts if a[0].endswith(".mp4") or "videos" in str(a[1])]


def test_broken_gl_warns_once_and_the_evaluation_goes_on(fresh_gl, monkeypatch, character, walk_run, caplog):
    monkeypatch.setenv("MUJOCO_GL", "no-such-backend")  # the child's `import mujoco` refuses it
    tracker = RecordingLogger()
    cfg = small_config()
    with caplog.at_level(logging.WARNING, logger="orchestrator.evaluation.video"):
        for iteration in (1, 2):
            metrics = evaluate_controller(cfg, character, walk_run, weights_of(character), tracker, iteration, False)
            assert np.isfinite(metrics["eval/time_until_fall_mean"])
        rec = Recording("x", np.zeros((2, character.model.nq)), None, character.model)
        assert write_videos([rec], Path("unused"), 30, W, H, run="test-run") == []
    warnings = [r for r in caplog.records if r.name == "orchestrator.evaluation.video"]
    assert len(warnings) == 1
    assert "MUJOCO_GL=no-such-backend" in warnings[0].getMessage() and "invalid value" in warnings[0].getMessage()
    assert not [a for a in tracker.artifacts if a[0].endswith(".mp4")]
    assert not video.videos_enabled(cfg, "test-run")
    # Another run in the same process is told once too.
    with caplog.at_level(logging.WARNING, logger="orchestrator.evaluation.video"):
        for _ in range(2):
            assert not video.videos_enabled(cfg, "another-run")
    assert len([r for r in caplog.records if r.name == "orchestrator.evaluation.video"]) == 2


@pytest.mark.parametrize("progress", [True, False])
def test_evaluation_shows_its_phases_on_a_progress_bar(character, walk_run, capsys, progress):
    cfg = small_config(video=False)
    cfg.progress = progress
    evaluate_controller(cfg, character, walk_run, weights_of(character), NoOpLogger(), 3, final=False)
    err = capsys.readouterr().err
    phases = ("time until fall", "tracking", "random sampling")
    if progress:
        assert "eval" in err and all(p in err for p in phases) and "0/3" in err
    else:
        assert not any(p in err for p in phases)
