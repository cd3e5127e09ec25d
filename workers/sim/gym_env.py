"""The humanoid tracking a reference clip, as a gymnasium environment (single and vector).

For peer comparisons (RLlib's PPO on the same character, `orchestrator.bench.peer_rllib`)
and for anyone who wants to train our character with another library.

- Observation: `workers.rewards.imitation_observation(s, s̃_{t+1})`, the simulated state
  s and the reference's state one control step ahead; float32 [2·D] (D = 16·bodies + 3,
  243 for the bundled character). Unbounded Box.
- Action: the 28 PD targets (rotation vectors of the ball joints, hinge angles).
  The simulator takes raw targets; the action space bounds them to [-π, π] per
  dimension (a rotation vector of norm π is already a half turn) and actions outside
  the box are clipped to it before they reach the simulator.
- Reward: `workers.rewards.imitation_reward` between the simulated state and the
  reference at the same time, in (0, 1] (1 exactly on the reference).
- terminated = fell | tracking_failed; truncated = timeout | clip_ended
  (`max_episode_steps` control steps, 300 = 10 s at 30 Hz by default).
- Reset is reference state initialisation from the motion library (start drawn
  from the library's start weights with the environment's seeded generator).

`HumanoidImitationVectorEnv` runs N environments in ONE `BatchedSim` stepped as a
batch: a library using it vectorises through our simulator rather than through N
Python environments. Finished environments reset automatically with gymnasium's
NEXT_STEP semantics by default (the step after an episode's end returns its reset
observation, reward 0, and ignores that environment's action), the only mode
RLlib's SingleAgentEnvRunner handles (it adds the observation that follows a done
step as the new episode's reset observation); SAME_STEP is available too. As
`BatchedSim` steps every environment, in NEXT_STEP mode an environment due for a
reset is stepped with the rest and then reset: a wasted control step per episode.

Both are registered on import as "MocapHumanoidImitation-v0":
`gymnasium.make("MocapHumanoidImitation-v0")` gives the single environment and
`gymnasium.make_vec(..., num_envs=N, vectorization_mode="vector_entry_point")` the
batched one.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from workers.body.character import Character
from workers.motion.library import MotionLibrary
from workers.rewards import DEFAULT_WEIGHTS, imitation_observation, imitation_reward
from workers.sim.env import SimConfig, Simulator, StepResult, make_sim

ENV_ID = "MocapHumanoidImitation-v0"
DEFAULT_CLIPS = ("humanoid3d_walk",)
ACTION_BOUND = float(np.pi)
_CAUSES = ("fell", "tracking_failed", "clip_ended", "timeout")


class _Tracking:
    """What the single and the vector environment share: the batched simulator and the
    observation, reward and episode-end rules over all its environments at once."""

    def __init__(
        self,
        num_envs: int,
        clips: Sequence[str | Path],
        sim_hz: float,
        control_hz: float,
        max_episode_steps: int,
        reward_weights: Mapping[str, float] | None,
        character: Character | None,
        library: MotionLibrary | None,
    ):
        self.character = character or Character.load()
        self.library = library or MotionLibrary.load(self.character, list(clips), fps=control_hz)
        config = SimConfig(sim_hz=sim_hz, control_hz=control_hz, max_episode_steps=max_episode_steps)
        self.sim = make_sim(self.character, self.library, num_envs, config)
        self.weights = dict(DEFAULT_WEIGHTS if reward_weights is None else reward_weights)
        obs_dim = 2 * self.sim.state_dim
        self.observation_space = spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        n_act = self.sim.action_dim
        self.action_space = spaces.Box(-ACTION_BOUND, ACTION_BOUND, (n_act,), np.float32)

    def observe(self, state: np.ndarray, env_ids: np.ndarray | None = None) -> np.ndarray:
        """Observations [len(env_ids), 2D] from the states s of those environments."""
        return imitation_observation(state, self.sim.reference_next_features(env_ids))

    def step(self, actions: np.ndarray) -> tuple[StepResult, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(result, observations [N, 2D], rewards [N], terminated [N], truncated [N]) of one control step."""
        a = np.clip(np.asarray(actions, dtype=np.float64), -ACTION_BOUND, ACTION_BOUND)
        result = self.sim.step(a.reshape(self.sim.num_envs, self.sim.action_dim))
        obs = self.observe(result.state)
        reward, _ = imitation_reward(self.character, result.kin, self.sim.reference_state(), self.weights)
        return result, obs, reward, result.fell | result.tracking_failed, result.timeout | result.clip_ended


def _causes(result: StepResult) -> dict[str, np.ndarray]:
    return {k: getattr(result, k) for k in _CAUSES}


class _CoreAccess:
    """The simulator, character and library behind an adapter."""

    _core: _Tracking

    @property
    def sim(self) -> Simulator:
        return self._core.sim

    @property
    def character(self) -> Character:
        return self._core.character

    @property
    def library(self) -> MotionLibrary:
        return self._core.library


class HumanoidImitationEnv(_CoreAccess, gymnasium.Env):
    """One humanoid tracking a reference clip (see the module docstring).

    Args:
        clips: bundled clip names or paths of the reference motions.
        sim_hz, control_hz: physics and policy rates.
        max_episode_steps: episode cap in control steps (truncation); 0 for none.
        reward_weights: the imitation reward's weights (default `workers.rewards.DEFAULT_WEIGHTS`).
        character, library: already loaded ones to share (the library must be at control_hz).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        clips: Sequence[str | Path] = DEFAULT_CLIPS,
        sim_hz: float = 480.0,
        control_hz: float = 30.0,
        max_episode_steps: int = 300,
        reward_weights: Mapping[str, float] | None = None,
        character: Character | None = None,
        library: MotionLibrary | None = None,
    ):
        self._core = _Tracking(1, clips, sim_hz, control_hz, max_episode_steps, reward_weights, character, library)
        self.observation_space = self._core.observation_space
        self.action_space = self._core.action_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.sim.rng = self.np_random  # seeded: the stream of np.random.default_rng(seed)
        state = self.sim.reset()
        return self._core.observe(state)[0], {}

    def step(self, action):
        result, obs, reward, terminated, truncated = self._core.step(action)
        info = {k: bool(v[0]) for k, v in _causes(result).items()}
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), info


class HumanoidImitationVectorEnv(_CoreAccess, VectorEnv):
    """N humanoids in one `BatchedSim`, stepped as a batch, with autoreset.

    Args: those of `HumanoidImitationEnv`, plus num_envs and autoreset_mode
    (NEXT_STEP, gymnasium's default and what RLlib expects, or SAME_STEP: finished
    environments reset in the step that ends them, their last observation and info in
    `infos["final_obs"]` / `infos["final_info"]`).

    Infos carry the episode-end causes (`fell`, `tracking_failed`, `clip_ended`,
    `timeout`) as [N] bool arrays with gymnasium's `_key` masks.
    """

    def __init__(
        self,
        num_envs: int = 16,
        clips: Sequence[str | Path] = DEFAULT_CLIPS,
        sim_hz: float = 480.0,
        control_hz: float = 30.0,
        max_episode_steps: int = 300,
        reward_weights: Mapping[str, float] | None = None,
        character: Character | None = None,
        library: MotionLibrary | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ):
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        if self.autoreset_mode == AutoresetMode.DISABLED:
            raise ValueError("HumanoidImitationVectorEnv autoresets: use NEXT_STEP or SAME_STEP")
        self._core = _Tracking(
            num_envs, clips, sim_hz, control_hz, max_episode_steps, reward_weights, character, library
        )
        self.num_envs = num_envs
        self.metadata = {"render_modes": [], "autoreset_mode": self.autoreset_mode}
        self.single_observation_space = self._core.observation_space
        self.single_action_space = self._core.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._autoreset = np.zeros(num_envs, bool)

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None):
        """Reset every environment. One generator drives the batch, so a list of seeds is
        folded into one (None entries ignored)."""
        if isinstance(seed, Sequence):
            given = [int(s) for s in seed if s is not None]
            seed = int(np.random.SeedSequence(given).generate_state(1)[0]) if given else None
        super().reset(seed=seed)
        self.sim.rng = self.np_random
        state = self.sim.reset()
        self._autoreset[:] = False
        return self._core.observe(state), {}

    def step(self, actions):
        result, obs, reward, terminated, truncated = self._core.step(actions)
        reward = reward.astype(np.float64)
        causes = _causes(result)
        infos: dict[str, Any] = {}
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            ids = np.flatnonzero(self._autoreset)
            if len(ids):  # their episode ended last step: this step is their reset
                obs[ids] = self._core.observe(self.sim.reset(ids), ids)
                reward[ids] = 0.0
                terminated[ids] = truncated[ids] = False
                for v in causes.values():
                    v[ids] = False
            self._autoreset = terminated | truncated
        else:  # SAME_STEP
            ids = np.flatnonzero(terminated | truncated)
            if len(ids):
                final_obs = np.full(self.num_envs, None, dtype=object)
                for i in ids:
                    final_obs[i] = obs[i].copy()
                mask = np.zeros(self.num_envs, bool)
                mask[ids] = True
                infos["final_obs"], infos["_final_obs"] = final_obs, mask
                infos["final_info"] = {k: v.copy() for k, v in causes.items()}
                infos["final_info"].update({"_" + k: mask.copy() for k in causes})
                infos["_final_info"] = mask.copy()
                obs[ids] = self._core.observe(self.sim.reset(ids), ids)
        for k, v in causes.items():
            infos[k], infos["_" + k] = v, np.ones(self.num_envs, bool)
        return obs, reward, terminated, truncated, infos


def make_vector_env(num_envs: int = 16, **kwargs) -> HumanoidImitationVectorEnv:
    """The vector entry point (`gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`)."""
    return HumanoidImitationVectorEnv(num_envs=num_envs, **kwargs)


def register() -> None:
    """Register ENV_ID with gymnasium (idempotent; done on import of this module)."""
    if ENV_ID in gymnasium.registry:
        return
    gymnasium.register(
        ENV_ID,
        entry_point=f"{__name__}:HumanoidImitationEnv",
        vector_entry_point=f"{__name__}:make_vector_env",
    )


register()
