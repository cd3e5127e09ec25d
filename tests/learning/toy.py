"""A tiny MuJoCo task that a learner can solve in seconds: hold a pendulum at a target angle.

One hinge under gravity, driven by a position servo (kp (target − θ), as the
humanoid's PD servos are): the action is the servo's target angle. Each episode
draws a target angle θ* and lasts a fixed number of control steps; every end is
a time limit (a truncation). Observation (cos θ, sin θ, θ̇, θ*); reward
exp(−k |θ − θ*|) after each control step, in (0, 1].

Because gravity pulls the arm off the servo's target, commanding θ* leaves a
steady error; the oracle commands the static equilibrium target
θ* + τ_g(θ*) / kp instead, with τ_g the gravity torque MuJoCo computes at θ*,
which holds the arm exactly at θ* once it has settled. Its return is an
achievable return to measure learners against (not an upper bound: a faster
transient can do slightly better).

N environments are N `MjData` on one `MjModel`, stepped one after another.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

PENDULUM_XML = """
<mujoco model="toy_pendulum">
  <option timestep="0.005" integrator="implicitfast"/>
  <worldbody>
    <body name="arm" pos="0 0 1">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="{damping}"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.04" mass="1"/>
    </body>
  </worldbody>
  <actuator>
    <position name="servo" joint="hinge" kp="{kp}" ctrlrange="-{ctrl_limit} {ctrl_limit}" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


@dataclass
class PendulumConfig:
    # Parallel environments.
    num_envs: int = 64
    # Control steps per episode.
    episode_steps: int = 50
    # Physics steps (5 ms each) per control step: 6 gives about 33 Hz control.
    substeps: int = 6
    # Target angles are drawn uniformly from [−target_range, target_range] rad (0 hangs straight down).
    target_range: float = 1.5
    # Initial angles are drawn uniformly from [−init_range, init_range] rad, at rest.
    init_range: float = 0.2
    # k in the reward exp(−k |θ − θ*|).
    reward_sharpness: float = 2.0
    # Servo stiffness (N m / rad); low enough that gravity (up to 4.9 N m) matters.
    kp: float = 10.0
    # Joint damping (N m s / rad).
    damping: float = 1.0
    # Servo targets are clipped to ±ctrl_limit rad.
    ctrl_limit: float = 2.5


@dataclass
class PendulumStep:
    """What one control step returns; arrays have N rows."""

    obs: np.ndarray  # [N, 4] observation to act on next (after any reset)
    reward: np.ndarray  # [N]
    done: np.ndarray  # [N] bool, the episode ended with this step
    truncated: np.ndarray  # [N] bool, it ended by the time limit (here: always when done)
    final_obs: np.ndarray  # [N, 4] observation reached by this step, before any reset


class PendulumTarget:
    obs_dim = 4
    act_dim = 1

    def __init__(self, config: PendulumConfig | None = None, seed: int = 0):
        self.config = cfg = config if config is not None else PendulumConfig()
        self.model = mujoco.MjModel.from_xml_string(
            PENDULUM_XML.format(kp=cfg.kp, damping=cfg.damping, ctrl_limit=cfg.ctrl_limit)
        )
        self.data = [mujoco.MjData(self.model) for _ in range(cfg.num_envs)]
        self.rng = np.random.default_rng(seed)
        self.target = np.zeros(cfg.num_envs)
        self.t = np.zeros(cfg.num_envs, dtype=np.int64)
        self._probe = mujoco.MjData(self.model)

    def reset(self) -> np.ndarray:
        """Start a new episode in every environment; returns obs [N, 4]."""
        return self._reset(np.arange(self.config.num_envs))

    def step(self, actions: np.ndarray) -> PendulumStep:
        """actions [N, 1] servo targets (rad). Finished environments are reset before returning."""
        cfg = self.config
        actions = np.asarray(actions, dtype=np.float64).reshape(cfg.num_envs)
        for d, a in zip(self.data, actions, strict=True):
            d.ctrl[0] = a
            for _ in range(cfg.substeps):
                mujoco.mj_step(self.model, d)
        self.t += 1
        final_obs = self._obs()
        theta = np.array([d.qpos[0] for d in self.data])
        error = np.angle(np.exp(1j * (theta - self.target)))  # wrapped to [−π, π]
        reward = np.exp(-cfg.reward_sharpness * np.abs(error))
        done = self.t >= cfg.episode_steps
        obs = self._reset(np.flatnonzero(done)) if done.any() else final_obs
        return PendulumStep(obs, reward, done, done.copy(), final_obs)

    def oracle_action(self) -> np.ndarray:
        """[N, 1] the servo target that holds each arm at rest exactly at its target angle."""
        cfg = self.config
        out = np.empty((cfg.num_envs, 1))
        for i, target in enumerate(self.target):
            self._probe.qpos[0], self._probe.qvel[0] = target, 0.0
            mujoco.mj_forward(self.model, self._probe)
            # At rest the servo must supply the bias (gravity) force: kp (a − θ*) = qfrc_bias.
            out[i, 0] = target + self._probe.qfrc_bias[0] / cfg.kp
        return out

    def _reset(self, ids: np.ndarray) -> np.ndarray:
        cfg = self.config
        self.target[ids] = self.rng.uniform(-cfg.target_range, cfg.target_range, len(ids))
        for i in ids:
            d = self.data[i]
            mujoco.mj_resetData(self.model, d)
            d.qpos[0] = self.rng.uniform(-cfg.init_range, cfg.init_range)
            mujoco.mj_forward(self.model, d)
        self.t[ids] = 0
        return self._obs()

    def _obs(self) -> np.ndarray:
        theta = np.array([d.qpos[0] for d in self.data])
        theta_dot = np.array([d.qvel[0] for d in self.data])
        return np.stack((np.cos(theta), np.sin(theta), theta_dot, self.target), axis=-1).astype(np.float32)


def mean_episode_return(env: PendulumTarget, policy: Callable[[np.ndarray], np.ndarray]) -> float:
    """Reset every environment, run one whole episode of `policy` (obs [N, 4] -> actions [N, 1]),
    and return the undiscounted return averaged over the N episodes."""
    obs = env.reset()
    total = np.zeros(env.config.num_envs)
    for _ in range(env.config.episode_steps):
        step = env.step(policy(obs))
        total += step.reward
        obs = step.obs
    return float(total.mean())
