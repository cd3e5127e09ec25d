"""Evaluation videos: MP4s of recorded rollouts, rendered offscreen in a child process and logged to the run.

`controller_videos` and `policy_videos` record what to show (`workers.evaluation.render`, a second or two of
simulation) and return a `RenderJob`: a child process renders and encodes the MP4s (imageio's ffmpeg
writer: H.264, yuv420p, playable in the MLflow UI) while the evaluation's other protocols run, and
`RenderJob.log` waits for them and logs them (`videos/<evaluation name>/` in `orchestrator.evaluation.protocols`).

The GL backend. MuJoCo picks its OpenGL platform from MUJOCO_GL once, when it is first imported, and by
then this process has imported it for the simulator, with whatever MUJOCO_GL said (usually nothing,
which means GLFW and a display). So the frames are rendered in a child process
(`python -m orchestrator.evaluation.video <job dir> <output dir>`) started with MUJOCO_GL set: the user's
MUJOCO_GL when there is one, else `egl` and then `osmesa` (both headless; EGL uses a GPU when there is one, Mesa's
llvmpipe otherwise). The first backend that works is kept for the rest of the process. A child also keeps a GL
crash (a driver's segfault) out of training. When no backend works, one warning per run names each
MUJOCO_GL tried and what failed, and the run goes on without videos (no further attempts).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from workers.evaluation.render import Recording

if TYPE_CHECKING:
    from orchestrator.schema import Config
    from orchestrator.tracking.base import RunLogger
    from workers.body.character import Character
    from workers.models.vae import VAEController
    from workers.motion.library import MotionLibrary
    from workers.policies import GaussianPolicy

log = logging.getLogger(__name__)

HEADLESS_BACKENDS = ("egl", "osmesa")
# The child's time limit: a start-up allowance plus this much per frame (software GL renders a
# 480 x 320 frame in about 10 ms; this allows for a machine 50 times slower).
TIMEOUT_BASE_S = 120.0
TIMEOUT_PER_FRAME_S = 0.5
_PROJECT_ROOT = Path(__file__).resolve().parents[1]


@dataclass
class _GLState:
    backend: str | None = None  # the MUJOCO_GL that worked
    failure: str | None = None  # why none did
    warned: set[str | None] = field(default_factory=set)  # runs that have had the warning


_GL = _GLState()


def backends() -> list[str]:
    """The MUJOCO_GL values to try, in order: the working one, else the user's, else the headless ones."""
    if _GL.backend is not None:
        return [_GL.backend]
    user = os.environ.get("MUJOCO_GL", "").strip()
    return [user] if user else list(HEADLESS_BACKENDS)


def videos_enabled(cfg: Config, run: str | None = None) -> bool:
    """Whether evaluations make videos: `eval.video` and a GL backend not already found broken (which
    `run` is told once)."""
    if cfg.eval.video and _GL.failure is not None:
        _warn(run)
    return bool(cfg.eval.video) and _GL.failure is None


# ----------------------------------------------------------------------------
# What to record, per kind of policy
# ----------------------------------------------------------------------------
def controller_videos(
    cfg: Config, character: Character, library: MotionLibrary, controller: VAEController, run: str | None = None
) -> RenderJob:
    """`eval.video_rollouts` time-until-fall rollouts and one tracked clip with its reference as a ghost,
    recorded now and rendering in the background (an empty job with `eval.video=false` or without GL)."""
    # Imported here, not above: the rendering child runs this module and needs none of it (nor torch).
    from orchestrator.world import evaluation_sim_config
    from workers.evaluation.render import record_fall_rollouts, record_tracking

    if not videos_enabled(cfg, run):
        return RenderJob([], 0.0, 0, 0, run)
    e, sim = cfg.eval, evaluation_sim_config(cfg)
    recordings = record_fall_rollouts(controller, character, library, e.video_rollouts, e.video_seconds, sim, cfg.seed)
    recordings.append(record_tracking(controller, character, library, e.video_seconds, sim, cfg.seed))
    return RenderJob(recordings, sim.control_hz, e.video_width, e.video_height, run)


def policy_videos(
    cfg: Config, character: Character, library: MotionLibrary, policy: GaussianPolicy, run: str | None = None
) -> RenderJob:
    """One episode of a PPO policy's deterministic actions from a reference start, its reference as a ghost,
    recorded now and rendering in the background (an empty job with `eval.video=false` or without GL)."""
    from orchestrator.world import evaluation_sim_config
    from workers.evaluation.render import record_policy_episode

    if not videos_enabled(cfg, run):
        return RenderJob([], 0.0, 0, 0, run)
    e, sim = cfg.eval, evaluation_sim_config(cfg)
    recording = record_policy_episode(policy.mean_action, character, library, e.video_seconds, sim, cfg.seed)
    return RenderJob([recording], sim.control_hz, e.video_width, e.video_height, run)


# ----------------------------------------------------------------------------
# Rendering in a child process, and logging
# ----------------------------------------------------------------------------
class RenderJob:
    """MP4s of recordings, rendered and encoded by a child process that runs while the caller goes on.

    `wait()` returns the files (trying the next GL backend, in the foreground, if the first failed);
    `log(logger, path)` waits and logs them; `close()` (or leaving a `with` block) stops the child if it
    still runs and deletes the files. Width and height are rounded down to even numbers (H.264 in
    yuv420p needs them even).
    """

    def __init__(self, recordings: list[Recording], fps: float, width: int, height: int, run: str | None = None):
        self.recordings, self.run = recordings, run
        self.dir: Path | None = None  # where the videos are written
        self._proc: subprocess.Popen | None = None
        self._paths: list[Path] | None = None
        self._errors: list[str] = []
        self._backends = backends()
        if _GL.failure is not None:
            _warn(run)
            self._paths = []
        elif not recordings:
            self._paths = []
        else:
            self.dir = Path(tempfile.mkdtemp(prefix="videos-"))
            self._job = self.dir / ".job"
            _write_job(self._job, recordings, fps, width, height)
            self._timeout = TIMEOUT_BASE_S + TIMEOUT_PER_FRAME_S * sum(r.frames for r in recordings)
            self._start()

    def _start(self) -> None:
        backend = self._backends[0]
        env = dict(os.environ, MUJOCO_GL=backend)
        if backend in HEADLESS_BACKENDS:
            env["PYOPENGL_PLATFORM"] = backend  # PyOpenGL's platform must agree with MuJoCo's
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(_PROJECT_ROOT), env.get("PYTHONPATH")]))
        command = [sys.executable, "-m", "orchestrator.evaluation.video", str(self._job), str(self.dir)]
        self._started, self._error = time.monotonic(), None
        with open(self._job / f"stderr-{len(self._errors)}.txt", "w") as stderr:  # a file: a pipe could fill up
            try:
                self._proc = subprocess.Popen(command, env=env, stdin=subprocess.DEVNULL, stdout=stderr, stderr=stderr)
            except OSError as err:
                self._proc = None
                self._error = f"could not start the render process: {err}"

    def _outcome(self) -> str | None:
        """Wait for the running child: None when it wrote every video, else a one-line reason."""
        if self._proc is None:
            return self._error
        try:
            code = self._proc.wait(timeout=max(self._timeout - (time.monotonic() - self._started), 1.0))
        except subprocess.TimeoutExpired:
            self._stop()
            return f"the render process took more than {self._timeout:.0f} s"
        self._proc = None
        if code == 0:
            return None
        text = (self._job / f"stderr-{len(self._errors)}.txt").read_text(errors="replace")
        lines = [line.strip() for line in text.splitlines() if line.strip()]
        return lines[-1] if lines else f"the render process exited with status {code}"

    def wait(self) -> list[Path]:
        """The MP4 files, one per recording in order ([] without a working GL backend)."""
        while self._paths is None:
            error = self._outcome()
            if error is None:
                _GL.backend = self._backends[0]
                self._paths = [self.dir / f"{r.name}.mp4" for r in self.recordings]
                break
            self._errors.append(f"MUJOCO_GL={self._backends.pop(0)}: {error}")
            if self._backends:
                self._start()
            else:
                _GL.failure = "; ".join(self._errors)
                _warn(self.run)
                self._paths = []
        return self._paths

    def log(self, logger: RunLogger, artifact_path: str) -> list[str]:
        """Wait for the videos and log each under `artifact_path`; the names logged."""
        paths = self.wait()
        for path in paths:
            logger.log_artifact(path, artifact_path)
        return [p.name for p in paths]

    def _stop(self) -> None:
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._proc = None

    def close(self) -> None:
        self._stop()
        if self.dir is not None:
            shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self) -> RenderJob:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _warn(run: str | None) -> None:
    if run in _GL.warned:
        return
    _GL.warned.add(run)
    log.warning(
        "evaluation videos are off for this run: offscreen rendering failed (%s). Set MUJOCO_GL to a working "
        "backend (egl or osmesa need libEGL or libOSMesa) or eval.video=false to silence this.",
        _GL.failure,
    )


def _write_job(job: Path, recordings: list[Recording], fps: float, width: int, height: int) -> None:
    job.mkdir()
    models: list[mujoco.MjModel] = []
    videos, arrays = [], {}
    for i, r in enumerate(recordings):
        if r.model is None:
            raise ValueError(f"recording {r.name!r} has no model")
        index = next((k for k, m in enumerate(models) if m is r.model), None)
        if index is None:
            index = len(models)
            models.append(r.model)
            mujoco.mj_saveModel(r.model, str(job / f"model-{index}.mjb"), None)
        arrays[f"qpos_{i}"] = np.asarray(r.qpos, np.float64)
        if r.ghost_qpos is not None:
            arrays[f"ghost_{i}"] = np.asarray(r.ghost_qpos, np.float64)
        videos.append({"name": r.name, "model": index, "ghost": r.ghost_qpos is not None})
    np.savez(job / "poses.npz", **arrays)
    spec = {"fps": float(fps), "width": int(width) // 2 * 2, "height": int(height) // 2 * 2, "videos": videos}
    (job / "job.json").write_text(json.dumps(spec))


def encode(frames: Iterable[np.ndarray], path: Path, fps: float) -> int:
    """Write RGB frames [H, W, 3] uint8 (even sizes) to an H.264 MP4 at `fps`; the number of frames."""
    import imageio.v2 as imageio

    count = 0
    writer = imageio.get_writer(
        path,
        format="FFMPEG",
        mode="I",
        fps=fps,
        codec="libx264",
        pixelformat="yuv420p",
        macro_block_size=2,
        ffmpeg_log_level="error",
        ffmpeg_params=["-movflags", "+faststart"],  # the index first: the browser plays it while loading
    )
    try:
        for frame in frames:
            writer.append_data(frame)
            count += 1
    finally:
        writer.close()
    return count


def _child(job: Path, out_dir: Path) -> None:
    """The render process: every video of a job written by `_write_job`, rendered with this MUJOCO_GL."""
    from workers.evaluation.render import render_frames

    spec = json.loads((job / "job.json").read_text())
    poses = np.load(job / "poses.npz")
    models: dict[int, mujoco.MjModel] = {}
    for i, video in enumerate(spec["videos"]):
        index = video["model"]
        if index not in models:
            models[index] = mujoco.MjModel.from_binary_path(str(job / f"model-{index}.mjb"))
        ghost = poses[f"ghost_{i}"] if video["ghost"] else None
        frames = render_frames(models[index], poses[f"qpos_{i}"], ghost, spec["width"], spec["height"])
        encode(frames, out_dir / f"{video['name']}.mp4", spec["fps"])


if __name__ == "__main__":
    _child(Path(sys.argv[1]), Path(sys.argv[2]))
