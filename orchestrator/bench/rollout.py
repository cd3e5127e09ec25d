"""`bench rollout`: the one rollout worker against raw `mj_step`, interleaved, for each kind of policy.

The worker is `workers.rollout.RolloutWorker` as the methods run it (collect
calls of `--collect` control steps over all its environments, everything it
records included), with:

- `vae`: the VAE controller (`VAEPolicy`), at the default run's laptop sizes;
- `vae-paper`: the same at ControlVAE's sizes (mixture of 6 experts of 3x512);
- `actor-critic`: the PPO actor-critic on the state (`GaussianPolicy`, AMP's
  policy input), policy and value MLPs of AMP's (1024, 512), with AMP's Φ(s) recorded;
- `tracker`: the tracking expert's residual actor-critic on s and s̃_{t+1}, with the
  imitation reward recorded, at its laptop sizes (512, 256);
- `task`: the point-goal task policy as PPO trains it (`TaskPPOPolicy`, σ = 0.5: the helper branch)
  on a frozen skill decoder of the laptop VAE's sizes, recording its task reward.

Raw and worker blocks alternate (`orchestrator.bench.sim.interleaved`): the raw side
replays the worker's own actions on one `MjData`, and the ratio is the median over
pairs of the worker's physics steps per second to the raw figure.
"""

from __future__ import annotations

import os
import platform
import time

import numpy as np
import torch

from orchestrator.bench.sim import RawStepper, interleaved, walk_run_setup
from workers.body.features import StateLayout
from workers.learners.base import cpu_seeded
from workers.learners.ppo import PPOConfig
from workers.learners.task import TaskConfig
from workers.learners.vae import VAEConfig, build_controller
from workers.models.actor_critic import ActorCritic
from workers.policies import GaussianPolicy, VAEPolicy
from workers.recorders import AMPFeatures, ImitationReward
from workers.rollout import RolloutWorker
from workers.sim.env import SimConfig
from workers.task.policy import TaskPPOPolicy

POLICIES = ("vae", "vae-paper", "actor-critic", "tracker", "task")
LAPTOP_VAE = VAEConfig(latent_dim=32, encoder_hidden=(256, 256), policy="mlp", policy_hidden=(256, 256))


def make_worker(kind: str, character, library, envs: int, config: SimConfig, seed: int) -> RolloutWorker:
    b, a = character.num_bodies, character.num_actions
    s = StateLayout(b).dim
    recorders: list = []
    if kind == "vae":
        policy = VAEPolicy(b, a, LAPTOP_VAE)
    elif kind == "vae-paper":
        policy = VAEPolicy(b, a, VAEConfig())
    elif kind == "actor-critic":
        policy = GaussianPolicy(ActorCritic(s, a, action_std=0.05), obs="state")
        recorders = [AMPFeatures(character)]
    elif kind == "tracker":
        net = ActorCritic(2 * s, a, action_std=0.05, policy_hidden=(512, 256), value_hidden=(512, 256))
        policy = GaussianPolicy(net, obs="imitation", residual=True)
        recorders = [ImitationReward(character)]
    elif kind == "task":
        policy = _task_policy(b, a, config.control_hz)
    else:
        raise ValueError(f"unknown policy {kind!r}; expected one of {POLICIES}")
    return RolloutWorker(character, library, envs, policy, config, seed=seed, recorders=recorders)


def _task_policy(num_bodies: int, action_dim: int, control_hz: float) -> TaskPPOPolicy:
    """The point-goal task policy under PPO with the helper branch, on a skill decoder of random weights."""
    with cpu_seeded(0):
        decoder = build_controller(num_bodies, action_dim, LAPTOP_VAE).state_dict()
    policy = TaskPPOPolicy(num_bodies, action_dim, TaskConfig(task="point_goal", sigma=0.5), control_hz, PPOConfig())
    policy.configure({"skill": {"config": LAPTOP_VAE, "module": decoder, "prior_action": True}})
    return policy


class WorkerRunner:
    """A rollout worker collecting in blocks; the latest block's actions feed the raw side."""

    def __init__(self, worker: RolloutWorker, collect: int):
        self.worker, self.collect = worker, collect
        self.sim = worker.sim
        self.actions: list[np.ndarray] = []
        self.control_steps = 0

    @property
    def episodes(self) -> int:
        return self.worker.episodes

    def block(self, seconds: float) -> float:
        steps, actions = 0, []
        wall0 = time.perf_counter()
        while time.perf_counter() - wall0 < seconds:
            traj = self.worker.collect(self.collect)
            actions.append(traj.actions.reshape(-1, traj.actions.shape[-1]))
            steps += traj.num_transitions
        rate = steps / (time.perf_counter() - wall0)
        self.actions = actions
        self.control_steps += steps
        return rate


def run(
    policies: list[str],
    envs: int,
    seconds: float,
    sim_hz: list[float],
    control_hz: float,
    collect: int,
    seed: int = 0,
    block_seconds: float = 0.5,
    threads: int = 1,
) -> dict:
    torch.set_num_threads(1)
    pairs = max(3, int(round(seconds / (2 * block_seconds))))
    rows = []
    for hz in sim_hz:
        character, library = walk_run_setup(hz, control_hz)
        config = SimConfig(sim_hz=hz, control_hz=control_hz, threads=threads)
        for kind in policies:
            worker = make_worker(kind, character, library, envs, config, seed)
            raw = RawStepper(character, library, config, seed)
            row = interleaved(raw, WorkerRunner(worker, collect), pairs, block_seconds)
            rows.append({"policy": kind, "sim_hz": hz, "substeps": config.substeps, **row})
    return {
        "benchmark": "rollout",
        "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "envs": envs,
        "collect": collect,
        "control_hz": control_hz,
        "threads": threads,
        "block_seconds": block_seconds,
        "pairs": pairs,
        "results": rows,
    }


def format_table(r: dict) -> str:
    lines = [
        f"rollout benchmark: one worker of {r['envs']} envs, collect({r['collect']}), control {r['control_hz']:g} Hz, "
        f"{r['threads']} physics thread(s); {r['pairs']} interleaved pairs of {r['block_seconds']:g} s",
        f"{'sim Hz':>7}  {'policy':<13}{'raw phys/s':>12}{'worker phys/s':>15}{'control/s':>11}{'ratio to raw':>14}"
        f"{'ratio IQR':>15}{'bad qacc':>10}",
    ]
    for x in r["results"]:
        q1, q3 = x["ratio_quartiles"]
        lines.append(
            f"{x['sim_hz']:>7g}  {x['policy']:<13}{x['raw_physics_steps_per_s']:>12,.0f}"
            f"{x['physics_steps_per_s']:>15,.0f}{x['control_steps_per_s']:>11,.0f}{x['physics_step_ratio']:>14.3f}"
            f"{f'{q1:.3f}-{q3:.3f}':>15}{x['bad_qacc_warnings']:>10}"
        )
    return "\n".join(lines)
