"""The AMP discriminator learns on real reference motion: walk transitions as data, run as policy.

Transitions are (Φ(s_t), Φ(s_t+1)) of the reference clips. Training uses the 30 Hz
transitions starting at frames t with t % 3 != 0; held out are those with t % 3 == 0
and every transition shifted by half a frame (odd frames of the clip resampled at
60 Hz to the frame two later), poses the training set never contains.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from workers.body.features import amp_dim, amp_features
from workers.learners.discriminator import DiscriminatorBatch, DiscriminatorConfig, DiscriminatorLearner
from workers.motion.library import MotionLibrary

WALK, RUN = "humanoid3d_walk", "humanoid3d_run"
HIDDEN = (256, 256)  # smaller than AMP's (1024, 512) to keep the tests fast
BATCH = 256


def transitions(character, lib: MotionLibrary, clip: str, frames: np.ndarray, step: int = 1) -> np.ndarray:
    """[N, 2·amp_dim] transitions from each frame to the frame `step` later (looping clips wrap)."""
    ids = np.full(len(frames), lib.clip_id(clip))
    now = amp_features(character, lib.state(ids, frames))
    nxt = amp_features(character, lib.state(ids, frames + step))
    return np.concatenate((now, nxt), axis=1)


@pytest.fixture(scope="module")
def motion(character, walk_run, clip_cache) -> dict[str, dict[str, np.ndarray]]:
    """{clip: {"train": [N, 210], "test": [M, 210]}} for walk and run."""
    at_60hz = MotionLibrary.load(character, [WALK, RUN], fps=60, cache_dir=clip_cache)
    out = {}
    for clip in (WALK, RUN):
        t = np.arange(walk_run.num_frames[walk_run.clip_id(clip)])
        half_shifted = transitions(character, at_60hz, clip, 2 * t + 1, step=2)
        out[clip] = {
            "train": transitions(character, walk_run, clip, t[t % 3 != 0]),
            "test": np.concatenate((transitions(character, walk_run, clip, t[t % 3 == 0]), half_shifted)),
        }
    return out


def train(
    motion: dict[str, dict[str, np.ndarray]],
    config: DiscriminatorConfig,
    steps: int,
    make_batch: Callable[[np.ndarray, np.ndarray, np.random.Generator], DiscriminatorBatch] | None = None,
) -> DiscriminatorLearner:
    """`steps` updates on minibatches drawn with a fixed seed; by default walk is data and run is policy."""
    rng = np.random.default_rng(0)
    learner = DiscriminatorLearner(motion[WALK]["train"].shape[1] // 2, config, seed=0)
    walk, run = motion[WALK]["train"], motion[RUN]["train"]
    for _ in range(steps):
        if make_batch is None:
            batch = DiscriminatorBatch(walk[rng.integers(0, len(walk), BATCH)], run[rng.integers(0, len(run), BATCH)])
        else:
            batch = make_batch(walk, run, rng)
        metrics = learner.update(batch)
    assert learner.skipped_updates == 0 and np.isfinite(metrics["loss"])
    return learner


@pytest.fixture(scope="module")
def trained(motion) -> Callable[..., DiscriminatorLearner]:
    """Walk-vs-run learners, trained once per (loss, w_gp) for the whole module."""
    cache: dict[tuple[str, float], DiscriminatorLearner] = {}

    def get(loss: str = "lsgan", w_gp: float = 10.0) -> DiscriminatorLearner:
        if (loss, w_gp) not in cache:
            cache[loss, w_gp] = train(motion, DiscriminatorConfig(hidden=HIDDEN, loss=loss, w_gp=w_gp), steps=200)
        return cache[loss, w_gp]

    return get


def test_transitions_are_amp_observations(character, motion):
    assert motion[WALK]["train"].shape[1] == 2 * amp_dim(character)
    assert len(motion[WALK]["test"]) > 40 and len(motion[RUN]["test"]) > 25


@pytest.mark.parametrize("loss", ["lsgan", "bce"])
def test_tells_held_out_walk_from_run(motion, trained, loss):
    learner = trained(loss)
    walk, run = motion[WALK]["test"], motion[RUN]["test"]
    acc_walk = float((learner.logits(walk) > 0).mean())
    acc_run = float((learner.logits(run) < 0).mean())
    print(f"{loss}: held-out accuracy walk {acc_walk:.3f} run {acc_run:.3f}")
    assert acc_walk >= 0.95 and acc_run >= 0.95
    # The style reward prefers walking: for lsgan near 1 on walk (D ≈ +1) and near 0 on run (D ≈ -1).
    r_walk, r_run = learner.reward(walk), learner.reward(run)
    print(f"{loss}: held-out style reward walk {r_walk.mean():.3f} run {r_run.mean():.3f}")
    assert r_walk.mean() > r_run.mean() + 0.5
    if loss == "lsgan":
        assert r_walk.mean() > 0.7 and r_run.mean() < 0.3


def test_gradient_penalty_flattens_the_discriminator_on_data(motion, trained):
    with_gp, without_gp = trained("lsgan", 10.0), trained("lsgan", 0.0)
    for split in ("train", "test"):
        batch = DiscriminatorBatch(motion[WALK][split], motion[RUN][split])
        norm_gp = with_gp.evaluate(batch)["input_grad_norm_data"]
        norm_free = without_gp.evaluate(batch)["input_grad_norm_data"]
        print(f"{split}: mean ‖∇φ D‖ on walk, w_gp=10: {norm_gp:.4f}, w_gp=0: {norm_free:.4f}")
        assert norm_gp < 0.9 * norm_free


def test_skill_conditioned_discriminator_uses_the_label(motion):
    """Data: (walk, skill 0) and (run, skill 1); policy: the same motions with the labels swapped.

    Only the pairing of motion and label tells the two sides apart.
    """

    def swapped(walk: np.ndarray, run: np.ndarray, rng: np.random.Generator) -> DiscriminatorBatch:
        half = BATCH // 2
        obs = np.concatenate((walk[rng.integers(0, len(walk), half)], run[rng.integers(0, len(run), half)]))
        skill = np.repeat([0, 1], half)
        return DiscriminatorBatch(obs, obs, skill, 1 - skill)

    learner = train(motion, DiscriminatorConfig(hidden=HIDDEN, num_skills=2), steps=300, make_batch=swapped)
    walk, run = motion[WALK]["test"], motion[RUN]["test"]
    obs = np.concatenate((walk, run))
    skill = np.repeat([0, 1], [len(walk), len(run)])
    acc_data = float((learner.logits(obs, skill) > 0).mean())
    acc_policy = float((learner.logits(obs, 1 - skill) < 0).mean())
    print(f"skills: held-out accuracy data {acc_data:.3f} policy {acc_policy:.3f}")
    assert acc_data >= 0.95 and acc_policy >= 0.95
