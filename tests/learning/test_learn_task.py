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
def test_model_based_heading_lowers_the_heading_error_in_the_simulator(character, walk_run, world_model, vae_runs):
    """ControlVAE §4.2 end to end: the task policy collects in the simulator (B_g), learns only through the frozen
    world model, and is judged in the simulator, from fixed starts with fixed goals, before and after."""
    from workers.evaluation.tasks import evaluate_task_policy
    from workers.learners.task import GoalBuffer
    from workers.rollout import RolloutWorker
    from workers.task_policy import TaskRolloutPolicy

    torch.manual_seed(0)
    vae, _ = vae_runs("conditional")
    skill = {"config": vae.config, "module": vae.vae.state_dict(), "prior_action": True}
    config = TaskConfig(task="heading", hidden=(128, 128), sigma=0.5, w_z=1.0, batch_size=64, lr=1e-3, optimizer="adam")
    learner = TaskLearner(vae.vae, world_model.model, 28, config)
    worker = RolloutWorker(character, walk_run, 16, TaskRolloutPolicy(15, 28, config, 30.0), seed=0)
    worker.policy.configure({"skill": skill})
    judge = TaskRolloutPolicy(15, 28, config, 30.0)
    judge.configure({"skill": skill})

    def heading_error() -> float:
        judge.set_weights(learner.get_weights())
        return evaluate_task_policy(judge, character, walk_run, 32, 4.0, seed=123)["terms"]["heading"]

    buffer, rng = GoalBuffer(4096), np.random.default_rng(0)
    before = heading_error()
    for _ in range(150):  # 150 collections of 16 x 16 states, 8 updates after each
        worker.set_weights(learner.get_weights())
        traj = worker.collect(16)
        buffer.add(traj.states, traj.extras["goal"])
        for _ in range(8):
            learner.update(buffer.sample(config.batch_size, config.rollout_steps, rng))
    after = heading_error()
    print(f"heading error in the simulator: {before:.3f} -> {after:.3f} rad")
    # The goals are uniform over all directions and the test's VAE saw two forward clips for 300 updates, so the
    # first seconds of every episode are a turn it barely has: the gain is small and varies with the seed. Measured
    # with 150 collections, seeds 0-3 (torch, worker and sampling): 1.622 -> 1.410, 1.504 -> 1.433, 1.622 -> 1.440,
    # 1.539 -> 1.510 rad (ratios 0.87-0.98). With 60 collections the change was within seed noise both ways
    # (0.92-0.98 before the elementwise heading rotation, 0.90-1.06 after it, which changes only float rounding).
    assert after < before
