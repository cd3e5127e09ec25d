"""Data for the learning tests: real trajectories of our humanoid, and a world model trained on them.

Trajectories come from the batched simulator tracking the walk and run clips with
noisy PD targets (the reference's next pose plus Gaussian noise), resetting the
environments that fall. Windows of consecutive transitions within one episode are
the training samples, as the replay buffer will hand them out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from workers.learners.base import Schedule
from workers.learners.vae import ControlVAEObjective, VAEBatch, VAELearner
from workers.learners.world_model import WorldModelBatch, WorldModelConfig, WorldModelLearner
from workers.models import body_state
from workers.sim.env import BatchedSim


@dataclass
class Trajectories:
    states: np.ndarray  # [T, N, B, 13] body state before each step
    next_states: np.ndarray  # [T, N, B, 13] its true successor (before any reset)
    actions: np.ndarray  # [T, N, A]
    done: np.ndarray  # [T, N] the environment was reset after this step
    clip_id: np.ndarray  # [T, N] reference clip of each state
    frame: np.ndarray  # [T, N] reference frame of each state

    def windows(self, length: int) -> np.ndarray:
        """(t, env) starts [W, 2] of every run of `length` transitions inside one episode."""
        t_max = len(self.done) - length + 1
        ok = np.ones((t_max, self.done.shape[1]), bool)
        for k in range(length - 1):
            ok &= ~self.done[k : k + t_max]
        return np.argwhere(ok)

    def states_window(self, starts: np.ndarray, length: int) -> np.ndarray:
        """Body states [W, length + 1, B, 13] of the windows."""
        t = starts[:, :1] + np.arange(length)
        env = starts[:, 1:]
        last = self.next_states[t[:, -1], env[:, 0]][:, None]
        return np.concatenate((self.states[t, env], last), axis=1)

    def batch(self, starts: np.ndarray, length: int) -> WorldModelBatch:
        t = starts[:, :1] + np.arange(length)
        actions = self.actions[t, starts[:, 1:]]
        return WorldModelBatch(torch.as_tensor(self.states_window(starts, length)), torch.as_tensor(actions))


def collect(character, library, num_envs: int, steps: int, noise: float, seed: int) -> Trajectories:
    sim = BatchedSim(character, library, num_envs, seed=seed)
    rng = np.random.default_rng(seed)
    out: dict[str, list[np.ndarray]] = {k: [] for k in Trajectories.__dataclass_fields__}
    for _ in range(steps):
        frames = sim.start_frame + sim.steps
        target = library.state(sim.clip_id, frames + 1)
        a = character.qpos_to_action(target.qpos) + rng.normal(0.0, noise, (num_envs, character.num_actions))
        out["states"].append(body_state.pack(sim.kin_state()))
        out["clip_id"].append(sim.clip_id.copy())
        out["frame"].append(frames)
        out["actions"].append(a.astype(np.float32))
        result = sim.step(a)
        out["next_states"].append(body_state.pack(result.kin))
        out["done"].append(result.done.copy())
        if result.done.any():
            sim.reset(np.flatnonzero(result.done))
    return Trajectories(**{k: np.stack(v) for k, v in out.items()})


@pytest.fixture(scope="session")
def trajectories(character, walk_run) -> Trajectories:
    """64 environments × 150 control steps (5 s) of noisy tracking: 9,600 transitions."""
    return collect(character, walk_run, num_envs=64, steps=150, noise=0.1, seed=0)


@pytest.fixture(scope="session")
def held_out(character, walk_run) -> Trajectories:
    return collect(character, walk_run, num_envs=16, steps=60, noise=0.1, seed=1)


WM_TEST_CONFIG = WorldModelConfig(hidden=(256, 256, 256), batch_size=128, rollout_steps=8, lr=1e-3)


def train_world_model(data: Trajectories, updates: int, seed: int = 0, config: WorldModelConfig = WM_TEST_CONFIG):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    learner = WorldModelLearner(data.states.shape[2], data.actions.shape[2], dt=1 / 30, config=config)
    starts = data.windows(config.rollout_steps)
    history = []
    for _ in range(updates):
        pick = starts[rng.integers(len(starts), size=config.batch_size)]
        history.append(learner.update(data.batch(pick, config.rollout_steps)))
    return learner, history


@pytest.fixture(scope="session")
def world_model_run(trajectories) -> tuple[WorldModelLearner, list[dict[str, float]]]:
    """A world model trained for 300 updates and its metrics, shared by the tests (frozen after)."""
    return train_world_model(trajectories, updates=300)


@pytest.fixture(scope="session")
def world_model(world_model_run) -> WorldModelLearner:
    return world_model_run[0]


def reference_windows(library, trajectories: Trajectories, n: int, steps: int, rng) -> np.ndarray:
    """Reference body states [n, steps + 1, B, 13] following random states of the trajectories."""
    t = rng.integers(trajectories.states.shape[0], size=n)
    env = rng.integers(trajectories.states.shape[1], size=n)
    return body_state.reference_windows(library, trajectories.clip_id[t, env], trajectories.frame[t, env], steps)


VAE_STEPS = 8


def train_vae(prior, library, trajectories, world_model, updates=300, seed=0):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    config = ControlVAEObjective(
        prior=prior,
        latent_dim=16,
        encoder_hidden=(128, 128),
        policy="mlp",
        policy_hidden=(256, 256),
        lr=3e-3,
        optimizer="adam",
        batch_size=64,
        rollout_steps=VAE_STEPS,
        beta=Schedule(0.01),
    )
    learner = VAELearner(15, 28, config, world_model=world_model.model, seed=seed)
    history = []
    for _ in range(updates):
        reference = torch.as_tensor(reference_windows(library, trajectories, config.batch_size, VAE_STEPS, rng))
        # Segments of the reference clips, started on the reference (the replay buffer would give
        # simulated starts; here the test isolates what the VAE learns).
        history.append(learner.update(VAEBatch(reference[:, :1], reference)))
    return learner, history


@pytest.fixture(scope="session")
def vae_runs(walk_run, trajectories, world_model):
    """Trained VAE learners and their metrics by prior type, each trained once per session."""
    runs = {}

    def get(prior):
        if prior not in runs:
            runs[prior] = train_vae(prior, walk_run, trajectories, world_model)
        return runs[prior]

    return get
