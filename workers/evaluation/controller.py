"""A VAE controller's evaluation: PhysicsVAE's and ControlVAE's protocols, run in the batched simulator.

- `time_until_fall` (PhysicsVAE Fig. 9, §5.5.1): every rollout starts from one
  fixed reference state, z is drawn from the prior at every control step, and a
  rollout ends at its first fall (a ground contact of a body other than the feet)
  or at `max_seconds`. Tracking termination and clip ends play no part.
- `tracking_error` (ControlVAE Fig. 14): every clip is divided into consecutive
  2-second segments, each tracked from its first frame with the posterior mean
  z = μ_q(s_t, s̃_{t+1}); the error is the mean over steps and non-root bodies of
  ‖(x_j − x_root) − (x̃_j − x̃_root)‖ in metres (AMP's Eq. 10 without time warping).
- `random_sampling` (ControlVAE Fig. 5): from random dataset states, z from the
  prior every control step for 200 steps; falls and distance travelled.

All batch their rollouts as the environments of one `Simulator` and run the
networks in eval mode without gradients; the controller's mode is restored after.
Actions are the policy's mean (no exploration noise).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from workers.body.character import Character
from workers.body.features import relative_position_error
from workers.models import body_state
from workers.models.nets import evaluation_mode, gaussian
from workers.models.vae import VAEController
from workers.motion.library import MotionLibrary
from workers.sim.env import SimConfig, Simulator, StepResult, make_sim, without_tracking_termination
from workers.sim.episodes import run_episodes

DEFAULT_START_CLIP = "humanoid3d_walk"

# A policy maps the simulator's current state to actions [N, A]; it can stand in for the controller.
Policy = Callable[[Simulator], np.ndarray]


def sim_features(sim: Simulator) -> torch.Tensor:
    """s [N, D] of the simulated characters, as the learners compute it (float32 body states)."""
    return body_state.features(torch.from_numpy(sim.body_states()))


def posterior_mean_action(controller: VAEController, sim: Simulator, bs: np.ndarray | None = None) -> np.ndarray:
    """a = μ_π(s, μ_q(s, goal)) [N, A] for the simulated characters (their body states `bs`, if read already):
    the controller tracking the reference, as the tracking evaluations and recordings drive it."""
    bs = sim.body_states() if bs is None else bs
    s = body_state.features(torch.from_numpy(bs))
    return posterior_mean(controller, s, sim.tracking_goal(controller.goal, bs)).cpu().numpy()


def prior_action(controller: VAEController, sim: Simulator, generator: torch.Generator) -> np.ndarray:
    """a = μ_π(s, z) [N, A] with z ~ p(z | s), for the simulated characters, on the controller's device; z's noise
    comes from `generator`, a CPU stream, and then moves, so that a seed draws the same z wherever the controller is
    (on the CPU, exactly `prior_dist(s).rsample(generator)`)."""
    device = next(controller.parameters()).device
    s = sim_features(sim).to(device)
    prior = controller.prior_dist(s)
    z = prior.rsample(eps=gaussian(prior.mean.shape, generator, prior.mean.dtype, device))
    return controller.act(s, z).cpu().numpy()


def posterior_mean(controller: VAEController, s: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """μ_π(s, μ_q(s, goal)) on the controller's device, whatever devices the state and goal come on (beside
    MuJoCo Warp on CUDA the goal is made on the GPU, the state read on the CPU)."""
    device = next(controller.parameters()).device
    s, goal = s.to(device), goal.to(device)
    posterior, _ = controller.encode(s, goal)
    return controller.act(s, posterior.mean)


def reference_targets(library: MotionLibrary) -> Policy:
    """A baseline policy: the PD targets of the reference's next pose (no feedback at all)."""

    def policy(sim: Simulator) -> np.ndarray:
        target = library.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        return sim.character.qpos_to_action(target.qpos)

    return policy


# ----------------------------------------------------------------------------
# Time until fall
# ----------------------------------------------------------------------------
def fall_start(library: MotionLibrary, start: tuple[str, int] | None = None) -> tuple[int, int]:
    """(clip id, frame) of the fixed start: `start`, else frame 0 of the walk clip, else of the first clip."""
    if start is None:
        name = DEFAULT_START_CLIP if DEFAULT_START_CLIP in library.names else library.names[0]
        start = (name, 0)
    name, frame = start
    clip = library.clip_id(name)
    if not 0 <= frame < library.num_frames[clip]:
        raise ValueError(f"start frame {frame} is outside clip {name!r} ({library.num_frames[clip]} frames)")
    return clip, int(frame)


def time_until_fall(
    controller: VAEController,
    character: Character,
    library: MotionLibrary,
    num_rollouts: int = 100,
    max_seconds: float = 60.0,
    start: tuple[str, int] | None = None,
    sim_config: SimConfig | None = None,
    seed: int = 0,
) -> dict:
    """Seconds until the first fall of `num_rollouts` rollouts driven by z ~ p(z | s) at every step.

    All rollouts start from the reference state of `start` = (clip name, frame) (see `fall_start`).
    A rollout that has not fallen after `max_seconds` counts as `max_seconds`. The simulation stops
    as soon as every rollout has fallen.

    Returns {"mean", "std", "median": seconds, "fallen": fraction that fell, "times": [num_rollouts]
    seconds}.
    """
    if num_rollouts < 1 or max_seconds <= 0:
        raise ValueError(f"need num_rollouts >= 1 and max_seconds > 0, got {num_rollouts} and {max_seconds}")
    config = without_tracking_termination(sim_config)
    clip, frame = fall_start(library, start)
    sim = make_sim(character, library, num_rollouts, config, seed=seed)
    sim.reset(np.arange(num_rollouts), np.full(num_rollouts, clip), np.full(num_rollouts, frame))
    generator = torch.Generator().manual_seed(seed)
    dt = 1.0 / config.control_hz
    max_steps = int(round(max_seconds * config.control_hz))
    fall_step = np.zeros(num_rollouts, int)  # 0: has not fallen

    def after(t: int, result: StepResult) -> bool:
        fall_step[(fall_step == 0) & result.fell] = t
        return bool((fall_step > 0).all())

    with evaluation_mode(controller):
        run_episodes(sim, lambda sim, _: prior_action(controller, sim, generator), max_steps, after, states=False)
    times = np.where(fall_step > 0, fall_step * dt, max_seconds)
    return {
        "mean": float(times.mean()),
        "std": float(times.std()),
        "median": float(np.median(times)),
        "fallen": float((fall_step > 0).mean()),
        "times": times.tolist(),
    }


# ----------------------------------------------------------------------------
# Tracking error
# ----------------------------------------------------------------------------
def tracking_segments(library: MotionLibrary, seconds: float, control_hz: float) -> tuple[np.ndarray, ...]:
    """ControlVAE Fig. 14's division of every clip into consecutive segments of `seconds`.

    (clip [S], start frame [S], control steps [S]): a clip of n frames has segments starting at
    frames 0, L, 2L, ... (L = seconds · control_hz steps) below n (a one-shot clip: below its last
    frame). A one-shot clip's last segment ends on its last frame; a cyclic clip's every segment
    runs L steps, through the next cycle where it must.
    """
    length = max(int(round(seconds * control_hz)), 1)
    clips, starts, steps = [], [], []
    for c in range(library.num_clips):
        n, loop = int(library.num_frames[c]), bool(library.loop[c])
        end = n if loop else n - 1  # a one-shot clip's last frame has no successor to track
        for start in range(0, max(end, 1), length):
            clips.append(c)
            starts.append(start)
            steps.append(length if loop else max(min(length, end - start), 1))
    return np.array(clips), np.array(starts), np.array(steps)


def tracking_error(
    controller: VAEController | None,
    character: Character,
    library: MotionLibrary,
    clip_seconds: float = 2.0,
    sim_config: SimConfig | None = None,
    seed: int = 0,
    policy: Policy | None = None,
) -> dict[str, float]:
    """Per clip, the mean body-position error relative to the root (metres) while tracking it.

    Every clip is divided into consecutive segments of `clip_seconds` (`tracking_segments`), as
    ControlVAE's Fig. 14 divides its sequences into 2-second clips; each segment is one environment
    started on the reference state of its first frame and driven by a = μ_π(s, μ_q(s, s̃_{t+1})) (or by
    `policy`, which replaces the controller, e.g. `reference_targets(library)`). A character that falls
    is not reset: it keeps trying and its error keeps counting, so a fall shows as a large error rather
    than as a shorter average.

    Returns {clip name: mean error over its segments' steps, ..., "mean": over every segment's steps
    (each second of data counts alike), "segments": how many}.
    """
    if controller is None and policy is None:
        raise ValueError("tracking_error needs a controller or a policy")
    config = without_tracking_termination(sim_config)
    clips, starts, steps = tracking_segments(library, clip_seconds, config.control_hz)
    n = len(clips)
    sim = make_sim(character, library, n, config, seed=seed)
    sim.reset(np.arange(n), clips, starts)
    total = np.zeros(n)

    def act(sim: Simulator, _: None) -> np.ndarray:
        return policy(sim) if policy is not None else posterior_mean_action(controller, sim)

    def after(t: int, result: StepResult) -> None:
        err = relative_position_error(result.kin.xpos, sim.reference_state().xpos)
        total[:] += np.where(t - 1 < steps, err, 0.0)

    with evaluation_mode(controller):
        run_episodes(sim, act, int(steps.max()), after, states=False)
    out = {name: float(total[clips == c].sum() / steps[clips == c].sum()) for c, name in enumerate(library.names)}
    out["mean"] = float(total.sum() / steps.sum())
    out["segments"] = float(n)
    return out


# ----------------------------------------------------------------------------
# Random sampling
# ----------------------------------------------------------------------------
def random_sampling(
    controller: VAEController,
    character: Character,
    library: MotionLibrary,
    num_rollouts: int = 32,
    seconds: float = 10.0,
    sim_config: SimConfig | None = None,
    seed: int = 0,
) -> dict:
    """ControlVAE's random sampling (Fig. 5): from random dataset states, z ~ p(z | s) every control step,
    for `seconds` of simulated time (ControlVAE: 200 steps at its 20 Hz, 10 s), round(seconds · control_hz)
    control steps at the simulator's rate.

    Starts are drawn uniformly over the library's frames (never a one-shot clip's last); nothing ends a
    rollout. Returns {"fell": fraction of rollouts that fell at least once, "distance": mean horizontal
    distance (m) from the start to the end, "path": mean horizontal path length of the root (m),
    "roots": [R, steps + 1, 2] root positions relative to each start, for the figure}.
    """
    config = without_tracking_termination(sim_config)
    steps = round(seconds * config.control_hz)
    if num_rollouts < 1 or steps < 1:
        raise ValueError(f"need num_rollouts >= 1 and at least one control step, got {num_rollouts} and {seconds} s")
    rng = np.random.default_rng(seed)
    usable = np.ones(library.total_frames, bool)
    usable[(library.offsets + library.num_frames - 1)[~library.loop & (library.num_frames > 1)]] = False
    rows = rng.choice(np.flatnonzero(usable), size=num_rollouts)
    clip_ids = np.searchsorted(library.offsets, rows, side="right") - 1
    sim = make_sim(character, library, num_rollouts, config, seed=seed)
    sim.reset(np.arange(num_rollouts), clip_ids, rows - library.offsets[clip_ids])
    generator = torch.Generator().manual_seed(seed)
    roots = np.empty((steps + 1, num_rollouts, 2))
    roots[0] = sim.kin_state().xpos[:, 0, :2]
    fell = np.zeros(num_rollouts, bool)

    def after(t: int, result: StepResult) -> None:
        fell[:] |= result.fell
        roots[t] = result.kin.xpos[:, 0, :2]

    with evaluation_mode(controller):
        run_episodes(sim, lambda sim, _: prior_action(controller, sim, generator), steps, after, states=False)
    roots = np.swapaxes(roots - roots[:1], 0, 1)
    return {
        "fell": float(fell.mean()),
        "distance": float(np.linalg.norm(roots[:, -1], axis=-1).mean()),
        "path": float(np.linalg.norm(np.diff(roots, axis=1), axis=-1).sum(1).mean()),
        "roots": roots,
    }
