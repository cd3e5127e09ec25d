"""Expert demonstrations: ten noisy rollouts per clip from the rollout worker, stored and split as a DemoSet."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from workers.body.features import StateLayout
from workers.demos import DemoError, DemoSet
from workers.learners.base import Weights
from workers.learners.ppo import PPOConfig, build_actor_critic
from workers.policies import ExpertPolicy
from workers.rollout import RolloutWorker
from workers.sim.env import SimConfig

PPO = PPOConfig(policy_hidden=(32,), value_hidden=(32,))


@pytest.fixture(scope="module")
def expert(character) -> Weights:
    """A residual tracking expert with zero offsets: PD tracking of the reference, which can be checked by hand."""
    torch.manual_seed(0)
    obs_dim = 2 * StateLayout(character.num_bodies).dim
    module = build_actor_critic(obs_dim, character.num_actions, PPO)
    state = {k: torch.zeros_like(v) if k.startswith("policy.") else v for k, v in module.state_dict().items()}
    module.load_state_dict(state)
    payload = {
        "kind": "ppo",
        "config": PPO,
        "observation": "imitation",
        "residual": True,
        "module": module.state_dict(),
    }
    return Weights(3, payload)


def demonstrate(character, library, expert, noise, per_clip=10, steps=12):
    policy = ExpertPolicy(character.num_bodies, character.num_actions, noise)
    worker = RolloutWorker(character, library, 8, policy, SimConfig(), seed=1)
    worker.set_weights(expert)
    clips = np.repeat(np.arange(library.num_clips), per_clip)
    episodes = worker.demonstrate(clips, np.full(len(clips), steps))
    for i, ep in enumerate(episodes):
        ep["rollout"] = i % per_clip
    return episodes, policy


def test_ten_noisy_rollouts_per_clip_with_the_stated_noise(character, walk_run, expert):
    episodes, _ = demonstrate(character, walk_run, expert, noise=0.05)
    clean, policy = demonstrate(character, walk_run, expert, noise=0.0)
    demos = DemoSet.from_episodes(episodes)
    assert np.bincount(demos.episode_clip).tolist() == [10] * walk_run.num_clips
    assert sorted(set(demos.episode_rollout.tolist())) == list(range(10))
    # Every rollout starts on its clip's frame 0; the first action is the expert's (here: the PD targets of the
    # reference's next frame) plus N(0, 0.05²) noise.
    first = np.stack([ep["actions"][0] for ep in episodes])
    target = np.stack([ep["actions"][0] for ep in clean])
    for c in range(walk_run.num_clips):
        ref = walk_run.state(np.array([c]), np.array([1]))
        assert np.allclose(target[[e["clip"] == c for e in clean]], character.qpos_to_action(ref.qpos), atol=1e-5)
    noise = first - target
    assert abs(noise.mean()) < 0.01
    assert noise.std() == pytest.approx(0.05, rel=0.1)
    # Episode ends: the last state of each episode, with no action after it; states chain within an episode.
    assert demos.done.sum() == demos.num_episodes and (demos.actions[demos.done] == 0).all()
    assert demos.num_transitions == sum(len(ep["actions"]) for ep in episodes)


def test_windows_never_cross_an_episode_end_and_the_split_holds_out_the_last_rollouts(character, walk_run, expert):
    episodes, _ = demonstrate(character, walk_run, expert, noise=0.05, per_clip=4, steps=6)
    demos = DemoSet.from_episodes(episodes)
    held = demos.episodes_of(True, holdout=1)
    assert set(demos.episode_rollout[held].tolist()) == {3}
    assert len(demos.episodes_of(False, holdout=1)) == 3 * walk_run.num_clips
    starts = demos.window_starts(3)
    for s in starts:
        assert len(set(demos.episode[s : s + 4].tolist())) == 1
    states, actions = demos.windows(starts[:5], 3)
    assert states.shape == (5, 4, character.num_bodies, 13) and actions.shape == (5, 3, character.num_actions)


def test_a_broken_demos_file_is_refused_with_its_name(tmp_path, character, walk_run, expert):
    episodes, _ = demonstrate(character, walk_run, expert, noise=0.05, per_clip=2, steps=4)
    path = DemoSet.from_episodes(episodes).save(tmp_path / "demos.npz")
    assert DemoSet.load(path).num_episodes == 2 * walk_run.num_clips
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(DemoError, match="junk.npz: unreadable demos file"):
        DemoSet.load(tmp_path / "junk.npz")
    arrays = dataclasses.asdict(DemoSet.load(path))
    del arrays["done"]
    np.savez(tmp_path / "partial.npz", **arrays)
    with pytest.raises(DemoError, match="partial.npz: no array 'done'"):
        DemoSet.load(tmp_path / "partial.npz")


def test_a_clips_expert_run_mirrored_on_its_mirror_gives_the_reflected_rollout(character, clip_cache):
    """One expert per clip, the mirrored clip driven by the original's expert mirrored (M∘π∘M): without noise,
    from frame 0, the mirror's rollout is the original's reflected, body by body and action by action, to rounding
    (MuJoCo's sums over the mirrored bodies run in another order), so the mirrored expert tracks the mirrored clip
    as well. A lopsided expert (random weights, offsets of ~0.1 rad) makes the check non-trivial. The rounding
    grows about 2x a step (the walk is chaotic: 1e-7 rad at the first action, 5e-5 at the ninth and 2e-2 at the
    sixteenth on an AMD EPYC here), so the reflection is compared over the first 8 steps, where a wrong map
    is off by ~0.1 from the first."""
    from workers.body.mirror import FLIP_XZ, FLIP_Y, action_mirror, mirror_maps
    from workers.motion.library import MotionLibrary

    library = MotionLibrary.load(character, ["humanoid3d_walk"], fps=30, mirror=True, cache_dir=clip_cache)
    torch.manual_seed(3)
    module = build_actor_critic(2 * StateLayout(character.num_bodies).dim, character.num_actions, PPO)
    with torch.no_grad():
        module.policy[-1].weight.mul_(300.0)  # the output layer starts at 0.01 scale: offsets of ~0.1 rad
    one = {"kind": "ppo", "config": PPO, "observation": "imitation", "residual": True, "module": module.state_dict()}
    payload = {"kind": "per_clip", "experts": [one], "clip_expert": [0, 0], "clip_mirrored": [False, True]}
    payload["mirror"] = mirror_maps(character)
    policy = ExpertPolicy(character.num_bodies, character.num_actions, noise=0.0)
    worker = RolloutWorker(character, library, 2, policy, SimConfig(), seed=0)
    worker.set_weights(Weights(1, payload))
    plain, mirrored = worker.demonstrate(np.array([0, 1]), np.array([20, 20]))
    assert min(len(plain["actions"]), len(mirrored["actions"])) >= 10
    steps = 8
    index, sign = action_mirror(character)
    offsets = plain["actions"][:steps] - character.qpos_to_action(
        library.state(np.zeros(steps, int), np.arange(1, steps + 1)).qpos
    )
    assert np.abs(offsets).max() > 0.05  # the expert does act on its own
    np.testing.assert_allclose(mirrored["actions"][:steps], plain["actions"][:steps, index] * sign, atol=1e-4)
    perm = character.body_mirror_perm()
    a, b = plain["states"][: steps + 1], mirrored["states"][: steps + 1]
    np.testing.assert_allclose(b[..., 0:3], a[:, perm, 0:3] * FLIP_Y, atol=1e-4)
    np.testing.assert_allclose(b[..., 3:7], a[:, perm, 3:7] * np.array([1.0, -1.0, 1.0, -1.0]), atol=1e-4)
    np.testing.assert_allclose(b[..., 10:13], a[:, perm, 10:13] * FLIP_XZ, atol=1e-3)
    assert plain["tracking_error"] == pytest.approx(mirrored["tracking_error"], rel=1e-3)  # over all 20 steps
