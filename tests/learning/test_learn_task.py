"""Model-based task learning: a heading policy on the frozen VAE lowers its loss through the frozen world model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from workers.learners.task import TaskBatch, TaskConfig, TaskLearner
from workers.models.body_state import yaw

STEPS = 16  # ControlVAE's T for task learning


def heading_batch(trajectories, n: int, rng: np.random.Generator) -> TaskBatch:
    """Simulated start states and a constant goal per rollout: a heading within 1 rad of the current one
    (16 steps are 0.53 s: not enough to turn around) and a speed in [0, 3] m/s."""
    t = rng.integers(trajectories.states.shape[0], size=n)
    env = rng.integers(trajectories.states.shape[1], size=n)
    start = torch.as_tensor(trajectories.states[t, env])
    heading = yaw(start[:, 0, 3:7]).numpy()
    goal = np.stack((heading + rng.uniform(-1.0, 1.0, n), rng.uniform(0.0, 3.0, n)), axis=-1)
    goals = np.repeat(goal[:, None], STEPS, axis=1).astype(np.float32)
    return TaskBatch(start, torch.as_tensor(goals))


def test_task_learner_lowers_heading_loss(trajectories, world_model, vae_runs):
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    vae, _ = vae_runs("conditional")
    config = TaskConfig(
        task="heading",
        hidden=(128, 128),
        sigma=0.5,
        w_z=1.0,
        rollout_steps=STEPS,
        batch_size=64,
        lr=1e-3,
        optimizer="adam",
    )
    learner = TaskLearner(vae.vae, world_model.model, 28, config)
    evaluation = heading_batch(trajectories, 256, np.random.default_rng(123))
    before = learner.evaluate(evaluation)
    history = [learner.update(heading_batch(trajectories, config.batch_size, rng)) for _ in range(300)]
    after = learner.evaluate(evaluation)
    print({k: (round(before[k], 3), round(after[k], 3)) for k in ("task", "heading", "speed", "fall", "latent")})
    assert all(math.isfinite(h["loss"]) for h in history)
    # The test's VAE saw two clips for 300 updates, so its latent space offers little to steer with; the
    # helper branch (σ = 0.5) carries most of the gain and the paper's w_z = 20 would pin μ_g to zero.
    # Measured: task 2.26 -> 1.94, heading 0.67 -> 0.58 rad. With σ = 0.1, w_z = 20: 2.27 -> 2.17.
    assert after["task"] < 0.9 * before["task"]
    assert after["heading"] < 0.9 * before["heading"]


@pytest.mark.slow
def test_model_based_heading_runs_end_to_end_in_the_simulator(character, walk_run, world_model, vae_runs):
    """ControlVAE §4.2 end to end: the task policy collects in the simulator (B_g), learns only through the frozen
    world model, and its new weights drive the simulator's policy, judged from fixed starts with fixed goals.
    What this asserts is the path, not learning in the simulator (below); learning through the world model is
    `test_task_learner_lowers_heading_loss`."""
    from workers.evaluation.tasks import evaluate_task_policy
    from workers.learners.task import GoalBuffer
    from workers.rollout import RolloutWorker
    from workers.task.policy import TaskRolloutPolicy

    vae, _ = vae_runs("conditional")
    torch.manual_seed(0)  # after the fixtures: whether they trained in this test or an earlier one must not matter
    skill = {"config": vae.config, "module": vae.vae.state_dict(), "prior_action": True}
    config = TaskConfig(task="heading", hidden=(128, 128), sigma=0.5, w_z=1.0, batch_size=64, lr=1e-3, optimizer="adam")
    learner = TaskLearner(vae.vae, world_model.model, 28, config)
    worker = RolloutWorker(character, walk_run, 16, TaskRolloutPolicy(15, 28, config, 30.0), seed=0)
    worker.policy.configure({"skill": skill})
    judge = TaskRolloutPolicy(15, 28, config, 30.0)
    judge.configure({"skill": skill})

    def in_simulator() -> dict:
        judge.set_weights(learner.get_weights())
        return evaluate_task_policy(judge, character, walk_run, 32, 4.0, seed=123)

    buffer, rng = GoalBuffer(4096), np.random.default_rng(0)
    before = in_simulator()
    history = []
    for _ in range(60):  # 60 collections of 16 x 16 states, 8 updates after each
        worker.set_weights(learner.get_weights())
        traj = worker.collect(16)
        assert traj.extras["goal"].shape == (16, 16, 2)  # B_g holds the goals the simulator's policy pursued
        buffer.add(traj.states, traj.extras["goal"])
        for _ in range(8):
            history.append(learner.update(buffer.sample(config.batch_size, config.rollout_steps, rng)))
    after = in_simulator()
    print(f"in the simulator: heading {before['terms']['heading']:.3f} -> {after['terms']['heading']:.3f} rad, ")
    print(f"time until fall {before['time_until_fall_mean']:.2f} -> {after['time_until_fall_mean']:.2f} s")
    assert learner.version == 480 and all(math.isfinite(h["loss"]) for h in history)
    assert judge.version == 480  # the judged policy runs the learner's newest weights ...
    assert after["terms"]["heading"] != before["terms"]["heading"]  # ... and they move the character
    # Not judged: the heading error in the simulator. Under this test's VAE (two clips, 300 updates) the character
    # falls in every 4 s episode after 0.7-0.8 s, before and after training, so that error is noise on falling
    # characters: over torch seeds 0-3 it went 1.566 -> 1.619, 1.504 -> 1.600, 1.488 -> 1.541, 1.539 -> 1.588 rad
    # (and with 150 collections 1.566 -> 1.620); before the learners' float-rounding changes of 2026-12-03 it
    # happened to fall (ratios 0.92-0.98), which this test used to assert.
