"""Evaluation in the loop: the papers' protocols on the current weights, as metrics, JSON and plots.

- time-until-fall (PhysicsVAE Fig. 9): one fixed start (the walk clip's frame 0, mid-stride: the paper
  does not say its start, and ours is not a standing pose), z from the prior every
  control step, `eval.fall_rollouts` rollouts capped at `eval.fall_max_seconds`.
- tracking error (ControlVAE Fig. 14): every clip divided into consecutive segments of
  `eval.tracking_seconds`, each tracked with the posterior; mean body-position error
  relative to the root, per clip and over all segments.
- random sampling (ControlVAE Fig. 5): `eval.random_rollouts` rollouts of
  `eval.random_seconds` (10 s, ControlVAE's) from random dataset states, z from the prior;
  the share that fell and the distance travelled, with the roots' paths as a figure.
- pose error after dynamic time warping (AMP Eq. 10, Table 3), for PPO policies:
  `eval.pose_episodes` episodes of up to `eval.pose_seconds`, with a figure of the
  error over time.
- videos (`orchestrator.evaluation.video`, with `eval.video`): time-until-fall rollouts and a tracked clip beside its
  reference, or one episode of a PPO policy beside its reference, as MP4s under `videos/<name>/`.

A progress bar ("eval", off with `progress=false`) names the phase running: evaluation at the paper's
sizes takes minutes.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from orchestrator.evaluation import video
from orchestrator.schema import Config
from orchestrator.tracking.base import RunLogger
from orchestrator.world import evaluation_sim_config
from workers.body.character import Character
from workers.evaluation.controller import random_sampling, time_until_fall, tracking_error
from workers.evaluation.imitation import pose_error_episodes
from workers.learners.base import Weights
from workers.learners.vae import build_controller
from workers.models.vae import VAEController
from workers.motion.library import MotionLibrary
from workers.policies import GaussianPolicy


def evaluate_controller(
    cfg: Config,
    character: Character,
    library: MotionLibrary,
    weights: Weights,
    logger: RunLogger,
    iteration: int,
    final: bool,
) -> dict[str, float]:
    controller = build_controller(character.num_bodies, character.num_actions, cfg.algo.vae)
    controller.load_state_dict(weights.state)
    controller.eval()
    name = "final" if final else f"iter-{iteration:07d}"
    videos = video.videos_enabled(cfg, logger.run_id)
    with Progress(cfg, 3 + 2 * videos) as progress, torch.no_grad():
        with progress.phase("video rollouts", skip=not videos):
            job = video.controller_videos(cfg, character, library, controller, logger.run_id)
        with job:  # renders in a child process while the protocols run
            fall, track, walk = _controller_protocols(cfg, character, library, controller, progress)
            with progress.phase("videos", skip=not videos):
                job.log(logger, f"videos/{name}")
    clips = {k: v for k, v in track.items() if k not in ("mean", "segments")}
    metrics = {
        "eval/time_until_fall_mean": float(fall["mean"]),
        "eval/time_until_fall_std": float(fall["std"]),
        "eval/time_until_fall_median": float(fall["median"]),
        "eval/tracking_error_mean": float(track["mean"]),
        "eval/random_sampling_fell": walk["fell"],
        "eval/random_sampling_distance": walk["distance"],
    }
    metrics.update({f"eval/tracking_error/{k}": float(v) for k, v in clips.items()})
    report = {
        "iteration": iteration,
        "policy_version": weights.version,
        "time_until_fall": fall,
        "tracking": track,
        "random_sampling": {k: v for k, v in walk.items() if k != "roots"},
    }
    logger.log_dict(jsonable(report), f"eval/{name}.json")
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / f"{name}.png"
        _plot(fall, clips, walk, png, f"policy version {weights.version}")
        logger.log_artifact(str(png), "eval")
    return metrics


def _controller_protocols(
    cfg: Config, character: Character, library: MotionLibrary, controller: VAEController, progress: Progress
) -> tuple[dict[str, Any], dict[str, float], dict[str, Any]]:
    """Time-until-fall, tracking error and random sampling of the controller."""
    with progress.phase("time until fall"):
        fall = time_until_fall(
            controller,
            character,
            library,
            num_rollouts=cfg.eval.fall_rollouts,
            max_seconds=cfg.eval.fall_max_seconds,
            sim_config=evaluation_sim_config(cfg),
            seed=cfg.seed,
        )
    with progress.phase("tracking"):
        track = tracking_error(
            controller,
            character,
            library,
            clip_seconds=cfg.eval.tracking_seconds,
            sim_config=evaluation_sim_config(cfg),
            seed=cfg.seed,
        )
    with progress.phase("random sampling"):
        walk = random_sampling(
            controller,
            character,
            library,
            num_rollouts=cfg.eval.random_rollouts,
            seconds=cfg.eval.random_seconds,
            sim_config=evaluation_sim_config(cfg),
            seed=cfg.seed,
        )
    return fall, track, walk


class Progress:
    """The evaluation's progress bar: `total` phases, each named while it runs (`with progress.phase(name)`)."""

    def __init__(self, cfg: Config, total: int):
        self.bar = tqdm(total=total, desc="eval", unit="phase", leave=False, disable=not cfg.progress)

    @contextlib.contextmanager
    def phase(self, name: str, skip: bool = False) -> Iterator[None]:
        """Name the phase on the bar while the block runs, and count it when done (unless `skip`)."""
        if not skip:
            self.bar.set_postfix_str(name)
        yield
        if not skip:
            self.bar.update(1)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.bar.close()


def jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def _plot(fall: dict[str, Any], track: dict[str, float], walk: dict[str, Any], path: Path, title: str) -> None:
    from matplotlib.figure import Figure  # imported when a figure is drawn: the benchmarks draw none

    fig = Figure(figsize=(15, 4))
    a, b, c = fig.subplots(1, 3)
    a.hist(np.asarray(fall["times"]), bins=20, color="tab:blue")
    a.set_xlabel("time until fall (s)")
    a.set_ylabel("rollouts")
    clips = sorted(track)
    b.barh(clips, [track[k] for k in clips], color="tab:orange")
    b.set_xlabel("tracking error (m), 2-second segments")
    for root in walk["roots"]:
        c.plot(root[:, 0], root[:, 1], lw=0.8)
    c.set_aspect("equal", adjustable="datalim")
    c.set_xlabel("x (m)")
    c.set_ylabel("y (m)")
    c.set_title(f"random sampling: {walk['fell']:.0%} fell, {walk['distance']:.1f} m travelled", fontsize=9)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def evaluate_imitation(
    cfg: Config,
    character: Character,
    library: MotionLibrary,
    policy: GaussianPolicy,
    logger: RunLogger,
    iteration: int,
    final: bool,
) -> dict[str, float]:
    """AMP's pose error after DTW (Table 3) for a PPO policy's deterministic actions, with its figure, and
    a video of one episode beside its reference."""
    name = "final" if final else f"iter-{iteration:07d}"
    videos = video.videos_enabled(cfg, logger.run_id)
    with Progress(cfg, 1 + 2 * videos) as progress:
        with progress.phase("video episode", skip=not videos):
            job = video.policy_videos(cfg, character, library, policy, logger.run_id)
        with job:  # renders in a child process while the episodes run
            with progress.phase("pose error"):
                pose = pose_error_episodes(
                    policy.mean_action,
                    character,
                    library,
                    num_episodes=cfg.eval.pose_episodes,
                    max_seconds=cfg.eval.pose_seconds,
                    sim_config=evaluation_sim_config(cfg),
                    seed=cfg.seed,
                )
            with progress.phase("videos", skip=not videos):
                job.log(logger, f"videos/{name}")
    metrics = {
        "eval/pose_error_dtw": pose["dtw"],
        "eval/pose_error_eq10": pose["dtw_eq10"],
        "eval/pose_error_per_frame": pose["per_frame"],
        "eval/episode_seconds": pose["seconds"],
    }
    logger.log_dict(jsonable({"iteration": iteration, "policy_version": policy.version, **pose}), f"eval/{name}.json")
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / f"pose-{name}.png"
        _plot_pose(pose, png, f"policy version {policy.version}")
        logger.log_artifact(str(png), "eval")
    return metrics


def _plot_pose(pose: dict[str, Any], path: Path, title: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.5))
    a, b = fig.subplots(1, 2)
    a.plot(pose["curve_t"], pose["curve"], color="tab:blue")
    a.set_xlabel("time (s)")
    a.set_ylabel("pose error after DTW (m)")
    a.set_title(f"mean {pose['dtw']:.3f} m (per frame {pose['per_frame']:.3f} m)", fontsize=9)
    b.hist([e["seconds"] for e in pose["episodes"]], bins=20, color="tab:orange")
    b.set_xlabel("episode length (s)")
    b.set_ylabel("episodes")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
