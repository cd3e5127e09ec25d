"""The rollout worker: M simulated characters tracking reference clips with the VAE controller.

ControlVAE's collection (§3.4, Alg. 1): each environment starts on a reference
state drawn from the library and tracks the clip with z from the posterior
q(z | s_t, s̃_{t+1}), s̃_{t+1} being the reference's next state; with probability
`prior_probability` an *episode* draws z from the prior p(z | s_t) at every step
instead (the paper chooses per trajectory; an episode is our trajectory). The
action is the policy's mean plus Gaussian noise of std `action_noise` (σ_π).
Finished environments (fall, tracking failure, clip end, timeout) are reset at
once from the library's start distribution.

Inference runs batched over the M environments, in eval mode and without
gradients. The worker owns its random streams (the simulator's resets, the
per-episode prior choice, z and the action noise), so the same seed and the same
weights give the same trajectories, and `state_dict` restores them all together
with the environments' physical state.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from workers.learners.base import Weights
from workers.learners.vae import VAEConfig, build_controller
from workers.models import body_state
from workers.motion.library import MotionLibrary
from workers.replay import Trajectory
from workers.sim.character import Character
from workers.sim.env import BatchedSim, SimConfig


class RolloutWorker:
    def __init__(
        self,
        character: Character,
        library: MotionLibrary,
        num_envs: int,
        vae_config: VAEConfig,
        sim_config: SimConfig | None = None,
        seed: int = 0,
        worker_id: int = 0,
        prior_probability: float = 0.4,
        action_noise: float = 0.05,
    ):
        if not 0.0 <= prior_probability <= 1.0:
            raise ValueError(f"prior_probability must be in [0, 1], got {prior_probability}")
        if action_noise < 0:
            raise ValueError(f"action_noise must be non-negative, got {action_noise}")
        self.library = library
        self.worker_id = worker_id
        self.prior_probability = prior_probability
        self.action_noise = action_noise
        sim_seed, np_seed, torch_seed = np.random.SeedSequence([seed, worker_id]).generate_state(3)
        self.sim = BatchedSim(character, library, num_envs, sim_config, seed=int(sim_seed))
        self.rng = np.random.default_rng(int(np_seed))
        self.generator = torch.Generator().manual_seed(int(torch_seed))
        # Networks are built under a fixed seed so that a worker that has not received weights yet
        # is deterministic too (and identical across workers).
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            self.controller = build_controller(character.num_bodies, character.num_actions, vae_config)
        self.controller.eval().requires_grad_(False)
        self.version = -1
        self.use_prior = self.rng.random(num_envs) < prior_probability  # [M] per episode
        # Counters for `stats`.
        self.steps_collected = 0
        self.episodes = 0
        self.episode_steps = 0  # summed length of the finished episodes
        self.ends = {"fell": 0, "tracking_failed": 0, "clip_ended": 0, "timeout": 0}
        self.collect_seconds = 0.0

    @property
    def num_envs(self) -> int:
        return self.sim.num_envs

    def set_weights(self, weights: Weights) -> None:
        """Load published VAE weights and remember their version."""
        self.controller.load_state_dict(weights.state)
        self.version = int(weights.version)

    @torch.no_grad()
    def act(self, bs: np.ndarray) -> np.ndarray:
        """Noisy actions [M, A] for body states bs [M, B, 13] at the environments' current frames."""
        s = body_state.features(torch.from_numpy(bs))
        frames = self.sim.start_frame + self.sim.steps
        ref_next = torch.from_numpy(self.library.features(self.sim.clip_id, frames + 1).astype(np.float32))
        posterior, prior = self.controller.encode(s, ref_next)
        use_prior = torch.from_numpy(self.use_prior)[:, None]
        mean = torch.where(use_prior, prior.mean, posterior.mean)
        log_std = torch.where(use_prior, prior.log_std, posterior.log_std)
        eps = torch.randn(mean.shape, generator=self.generator)
        z = mean + log_std.exp() * eps
        a = self.controller.act(s, z)
        a = a + self.action_noise * torch.randn(a.shape, generator=self.generator)
        return a.numpy()

    def collect(self, steps: int) -> Trajectory:
        """Run every environment for `steps` control steps; the trajectory, tagged with the weights' version."""
        t0 = time.perf_counter()
        sim, m = self.sim, self.num_envs
        states = np.empty((steps, m, sim.character.num_bodies, 13), np.float32)
        next_states = np.empty_like(states)
        actions = np.empty((steps, m, sim.action_dim), np.float32)
        done = np.empty((steps, m), bool)
        clip_id = np.empty((steps, m), np.int64)
        frame = np.empty((steps, m), np.int64)
        bs = body_state.pack(sim.kin_state())
        for t in range(steps):
            states[t] = bs
            clip_id[t] = sim.clip_id
            frame[t] = sim.start_frame + sim.steps
            a = self.act(bs)
            actions[t] = a
            result = sim.step(a)
            next_states[t] = body_state.pack(result.kin)
            done[t] = result.done
            bs = next_states[t]
            if result.done.any():
                ids = np.flatnonzero(result.done)
                self._count_ends(result, ids)
                sim.reset(ids)
                self.use_prior[ids] = self.rng.random(len(ids)) < self.prior_probability
                bs = bs.copy()
                bs[ids] = body_state.pack(sim.kin_state()[ids])
        self.steps_collected += steps * m
        self.collect_seconds += time.perf_counter() - t0
        return Trajectory(states, next_states, actions, done, clip_id, frame, self.version, self.worker_id)

    def _count_ends(self, result, ids: np.ndarray) -> None:
        self.episodes += len(ids)
        self.episode_steps += int(self.sim.steps[ids].sum())
        for key in self.ends:
            self.ends[key] += int(getattr(result, key)[ids].sum())

    def stats(self) -> dict[str, float]:
        """Totals since the worker was built: steps, finished episodes and why they ended, throughput."""
        out = {
            "steps": float(self.steps_collected),
            "episodes": float(self.episodes),
            "mean_episode_length": self.episode_steps / self.episodes if self.episodes else 0.0,
            "falls": float(self.ends["fell"]),
            "tracking_failures": float(self.ends["tracking_failed"]),
            "clip_ends": float(self.ends["clip_ended"]),
            "timeouts": float(self.ends["timeout"]),
            "steps_per_second": self.steps_collected / self.collect_seconds if self.collect_seconds else 0.0,
            "version": float(self.version),
        }
        return out

    # Checkpoints -----------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """RNG states, counters and the environments' state: NumPy arrays and plain types.

        The weights are not included (the learner publishes them); restoring into a worker with the
        same weights continues the same trajectories.
        """
        sim = self.sim
        return {
            "version": self.version,
            "rng": self.rng.bit_generator.state,
            "sim_rng": sim.rng.bit_generator.state,
            "generator": self.generator.get_state().numpy().copy(),
            "use_prior": self.use_prior.copy(),
            "counters": {
                "steps_collected": self.steps_collected,
                "episodes": self.episodes,
                "episode_steps": self.episode_steps,
                "collect_seconds": self.collect_seconds,
                **{f"ends.{k}": v for k, v in self.ends.items()},
            },
            "envs": {
                "qpos": sim._qpos.copy(),
                "qvel": sim._qvel.copy(),
                "qacc_warmstart": np.stack([d.qacc_warmstart.copy() for d in sim.datas]),
                "clip_id": sim.clip_id.copy(),
                "start_frame": sim.start_frame.copy(),
                "steps": sim.steps.copy(),
                "bad_head_steps": sim._bad_head_steps.copy(),
            },
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        sim = self.sim
        envs = state["envs"]
        if len(envs["clip_id"]) != self.num_envs:
            raise ValueError(
                f"worker state is for {len(envs['clip_id'])} environments, this worker has {self.num_envs}"
            )
        self.version = int(state["version"])
        self.rng.bit_generator.state = state["rng"]
        sim.rng.bit_generator.state = state["sim_rng"]
        self.generator.set_state(torch.from_numpy(np.asarray(state["generator"], np.uint8).copy()))
        self.use_prior = np.asarray(state["use_prior"], bool).copy()
        c = state["counters"]
        self.steps_collected = int(c["steps_collected"])
        self.episodes = int(c["episodes"])
        self.episode_steps = int(c["episode_steps"])
        self.collect_seconds = float(c["collect_seconds"])
        self.ends = {k: int(c[f"ends.{k}"]) for k in self.ends}
        ids = np.arange(self.num_envs)
        sim.set_state(ids, envs["qpos"], envs["qvel"])
        for d, w in zip(sim.datas, envs["qacc_warmstart"], strict=True):
            d.qacc_warmstart[:] = w  # set_state zeroes the solver's warm start; the next step reads it
        sim.clip_id[:] = envs["clip_id"]
        sim.start_frame[:] = envs["start_frame"]
        sim.steps[:] = envs["steps"]
        sim._bad_head_steps[:] = envs["bad_head_steps"]
