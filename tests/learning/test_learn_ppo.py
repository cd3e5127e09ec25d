"""PPO learns a tiny MuJoCo task to within 10% of an oracle controller's return, in seconds.

The task (workers/sim/toy.py): hold a pendulum, driven by a position servo under
gravity, at a random target angle; reward exp(−2 |θ − θ*|) per step, 50 steps an
episode. The oracle commands the gravity-compensated servo target that holds the
arm exactly at θ*; its return is achievable, and the baselines below show that
reaching 90% of it requires learning the gravity compensation, not just
commanding θ*.

The PPO settings here are for a problem this small (Adam, clip 0.2, action std
0.2, (64, 64) networks), not AMP's (SGD at 2e-6, clip 0.02), which are tuned
for hours of humanoid training.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from toy import PendulumConfig, PendulumTarget, mean_episode_return  # beside this file

from workers.learners.ppo import PPOConfig, PPOLearner, Rollout

CONFIG = PPOConfig(
    policy_hidden=(64, 64),
    value_hidden=(64, 64),
    activation="relu",
    action_std=0.2,
    optimizer="adam",
    policy_lr=1e-3,
    value_lr=1e-3,
    gamma=0.95,
    lam=0.95,
    clip=0.2,
    epochs=5,
    minibatch_size=256,
    seed=0,
)
ROLLOUT_STEPS = 32  # × 64 environments = 2048 samples per iteration; episodes (50 steps) end mid-rollout
EVAL = PendulumConfig(num_envs=256)


def train(iterations: int, seed: int = 0) -> PPOLearner:
    env = PendulumTarget(PendulumConfig(num_envs=64), seed=seed)
    learner = PPOLearner(env.obs_dim, env.act_dim, CONFIG)
    obs = env.reset()
    for _ in range(iterations):
        steps: list[dict[str, np.ndarray]] = []
        for _ in range(ROLLOUT_STEPS):
            actions, log_probs, values = learner.act(obs)
            step = env.step(actions)
            steps.append(
                dict(
                    obs=obs,
                    actions=actions,
                    log_probs=log_probs,
                    values=values,
                    rewards=step.reward,
                    dones=step.done,
                    truncated=step.truncated,
                    final_obs=step.final_obs,
                )
            )
            obs = step.obs
        rollout = Rollout(last_obs=obs, **{k: np.stack([s[k] for s in steps]) for k in steps[0]})
        metrics = learner.train_on_rollout(rollout)
        assert metrics["skipped_updates"] == 0.0
    return learner


def test_oracle_holds_the_arm_at_its_target():
    env = PendulumTarget(PendulumConfig(num_envs=8), seed=5)
    env.reset()
    for _ in range(env.config.episode_steps - 1):
        step = env.step(env.oracle_action())
    theta = np.arctan2(step.final_obs[:, 1], step.final_obs[:, 0])
    np.testing.assert_allclose(theta, env.target, atol=1e-3)


def test_ppo_reaches_90_percent_of_the_oracle_return():
    start = time.perf_counter()
    learner = train(iterations=60)
    seconds = time.perf_counter() - start

    def returns(policy) -> float:
        return mean_episode_return(PendulumTarget(EVAL, seed=123), policy)  # the same 256 episodes each time

    oracle_env = PendulumTarget(EVAL, seed=123)
    oracle = mean_episode_return(oracle_env, lambda obs: oracle_env.oracle_action())
    ppo = returns(lambda obs: learner.act(obs, deterministic=True)[0])
    still = returns(lambda obs: np.zeros((len(obs), 1)))
    naive = returns(lambda obs: obs[:, 3:4])  # command θ*, no gravity compensation
    print(f"\nreturns over 50 steps: ppo {ppo:.2f}, oracle {oracle:.2f}, naive {naive:.2f}, zero {still:.2f}")
    print(f"training: {seconds:.1f} s")
    assert naive < 0.9 * oracle and still < 0.9 * oracle  # the bar needs learning
    assert ppo >= 0.9 * oracle
    assert seconds < 120


def test_training_is_deterministic():
    a, b = train(iterations=2), train(iterations=2)
    for k, v in a.module.state_dict().items():
        torch.testing.assert_close(v, b.module.state_dict()[k], rtol=0, atol=0)
