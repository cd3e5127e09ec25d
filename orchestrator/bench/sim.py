"""Simulation benchmark: raw MuJoCo stepping against the batched simulator.

The figures are single-threaded unless `threads` says otherwise (MuJoCo steps
on the calling thread; torch is limited to one thread), so the ratio says how
much of a core the simulator's own work costs on top of the physics.

Interleaved, because these machines are shared: a raw figure and a batched
figure measured in separate 5 s blocks drifted apart by up to 15% from run to
run (ratios 0.75-0.91 in five runs), as other jobs came and went. Here each
policy's measurement is a series of pairs of short blocks (`block_seconds`,
0.25 s by default), one raw and one batched, the order alternating from pair
to pair (raw first, then batched first) so that a steady drift cancels. Each
pair gives a ratio; the report is the median of the pairwise ratios with its
quartiles, and the median of each side's rates. One untimed block of each side
runs first (warm caches, torch's first call).

- raw: `mj_step(nstep=K)` on one `MjData`, timed around the call only. Its
  controls replay the action rows the batched side's policy produced in its
  latest block, so both sides see the same action distribution, and it is
  reset the way the simulator resets: to a reference start drawn from the
  library, when a geom other than the allowed ones touches the floor.
- batched: `BatchedSim.step` with the policy's targets, wall time of the whole
  loop: policy inference, state features, termination checks and resets of
  finished environments included.
- random policy: Gaussian PD targets (σ = 0.1 rad) around the zero pose.
- MLP policy: the targets come from an MLP of ControlVAE's size
  (s → 3×512 ELU → 28) evaluated on the whole batch each control step.
- ratio: the batched simulator's physics steps per second over the raw figure
  of the same pair.
- stability: mjWARN_BADQACC warnings (non-finite or huge accelerations, after
  which MuJoCo resets the environment) raised during the batched blocks, with the
  physics steps they were counted over; the raw side's count is reported too.
"""

from __future__ import annotations

import os
import platform
import time

import mujoco
import numpy as np

from workers.body.character import Character
from workers.motion.library import MotionLibrary
from workers.sim.env import BatchedSim, SimConfig

NOISE = 0.1
BADQACC = int(mujoco.mjtWarning.mjWARN_BADQACC)


def walk_run_setup(sim_hz: float, control_hz: float) -> tuple[Character, MotionLibrary]:
    character = Character.load(sim_hz=sim_hz)
    library = MotionLibrary.load(character, ["humanoid3d_walk"], fps=control_hz)
    return character, library


class RawStepper:
    """One MjData stepped K substeps per call, reset like the batched simulator's environments."""

    def __init__(self, character: Character, library: MotionLibrary, config: SimConfig, seed: int):
        self.model, self.library, self.k = character.model, library, config.substeps
        self.data = mujoco.MjData(self.model)
        self.rng = np.random.default_rng(seed)
        allowed = [self.model.geom(n).id for n in config.allowed_contacts] + [character.floor_geom]
        self.fall_geom = np.ones(self.model.ngeom, bool)
        self.fall_geom[allowed] = False
        self.actions = np.zeros((1, self.model.nu))  # rows replayed as controls, one per call
        self.row = 0
        self.calls = self.episodes = 0
        self.reset()

    def reset(self) -> None:
        clip, frame = self.library.sample_starts(1, self.rng)
        ref = self.library.state(clip, frame)
        d = self.data
        d.time, d.qpos[:], d.qvel[:], d.qacc_warmstart[:] = 0.0, ref.qpos[0], ref.qvel[0], 0.0
        mujoco.mj_forward(self.model, d)
        self.episodes += 1

    def block(self, seconds: float) -> float:
        """Physics steps per second of busy time over a block of `seconds` wall time."""
        m, d, k = self.model, self.data, self.k
        stepped, busy, wall0 = 0, 0.0, time.perf_counter()
        while time.perf_counter() - wall0 < seconds:
            d.ctrl[:] = self.actions[self.row % len(self.actions)]
            self.row += 1
            t0 = time.perf_counter()
            mujoco.mj_step(m, d, nstep=k)
            busy += time.perf_counter() - t0
            stepped += k
            self.calls += 1
            # Contacts of the last substep's start: a fall is seen one substep late, which
            # changes the workload by nothing that matters and keeps the timed call plain.
            if d.ncon and self.fall_geom[d.contact.geom].any():
                self.reset()
        return stepped / busy

    @property
    def bad_qacc_warnings(self) -> int:
        return int(self.data.warning[BADQACC].number)


class BatchedRunner:
    """A BatchedSim driven by a policy in blocks, keeping the latest block's actions for the raw side."""

    def __init__(self, sim: BatchedSim, policy):
        self.sim, self.policy = sim, policy
        self.state = sim.reset()
        self.actions: list[np.ndarray] = []
        self.control_steps = self.episodes = 0

    def block(self, seconds: float) -> float:
        """Control steps per second (all environments) over a block of `seconds` wall time."""
        sim, steps, actions = self.sim, 0, []
        wall0 = time.perf_counter()
        while time.perf_counter() - wall0 < seconds:
            action = self.policy(self.state)
            actions.append(action)
            result = sim.step(action)
            self.state = result.state
            done = np.flatnonzero(result.done)
            if done.size:
                self.state[done] = sim.reset(done)
                self.episodes += done.size
            steps += 1
        rate = steps * sim.num_envs / (time.perf_counter() - wall0)
        self.actions = actions
        self.control_steps += steps * sim.num_envs
        return rate


def mlp(state_dim: int, action_dim: int, seed: int):
    """An MLP of ControlVAE's policy size (s -> 3x512 ELU -> actions), in eval mode, its weights drawn from `seed`."""
    import torch

    torch.manual_seed(seed)
    return torch.nn.Sequential(
        torch.nn.Linear(state_dim, 512), torch.nn.ELU(),
        torch.nn.Linear(512, 512), torch.nn.ELU(),
        torch.nn.Linear(512, 512), torch.nn.ELU(),
        torch.nn.Linear(512, action_dim),
    ).eval()  # fmt: skip


def make_mlp_policy(state_dim: int, action_dim: int, seed: int, device: str = "cpu"):
    """`mlp` as a NumPy-in, NumPy-out policy whose network runs on `device` (the state is copied there and the
    actions back, as a rollout worker's policy does on its simulator's device)."""
    import torch

    net = mlp(state_dim, action_dim, seed).to(device)

    def policy(state: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return net(torch.from_numpy(state).to(device)).cpu().numpy()

    return policy


def interleaved(raw: RawStepper, batched: BatchedRunner, pairs: int, block_seconds: float) -> dict:
    """Median rates and pairwise ratio of `pairs` alternating raw/batched blocks."""
    k, sim = raw.k, batched.sim
    batched.block(block_seconds)  # untimed warm-up; also gives the raw side its first actions
    raw.actions = np.concatenate(batched.actions)
    raw.block(block_seconds)
    warn0, raw_warn0 = int(sim.warning_counts().sum()), raw.bad_qacc_warnings
    steps0, episodes0 = batched.control_steps, batched.episodes
    raw_calls0, raw_episodes0 = raw.calls, raw.episodes
    raw_rates, control_rates = [], []
    for p in range(pairs):
        if p % 2 == 0:
            raw_rates.append(raw.block(block_seconds))
            control_rates.append(batched.block(block_seconds))
        else:
            control_rates.append(batched.block(block_seconds))
            raw_rates.append(raw.block(block_seconds))
        raw.actions = np.concatenate(batched.actions)
    raw_rates, control_rates = np.array(raw_rates), np.array(control_rates)
    ratios = control_rates * k / raw_rates
    control_steps = batched.control_steps - steps0
    raw_calls = raw.calls - raw_calls0
    return {
        "pairs": pairs,
        "raw_physics_steps_per_s": float(np.median(raw_rates)),
        "control_steps_per_s": float(np.median(control_rates)),
        "physics_steps_per_s": float(np.median(control_rates)) * k,
        "physics_step_ratio": float(np.median(ratios)),
        "ratio_quartiles": [float(q) for q in np.quantile(ratios, [0.25, 0.75])],
        "bad_qacc_warnings": int(sim.warning_counts().sum()) - warn0,
        "batched_physics_steps": control_steps * k,
        "raw_bad_qacc_warnings": raw.bad_qacc_warnings - raw_warn0,
        "raw_physics_steps": raw_calls * k,
        # Workload check: mean episode length in control steps on each side.
        "episode_steps": control_steps / max(batched.episodes - episodes0, 1),
        "raw_episode_steps": raw_calls / max(raw.episodes - raw_episodes0, 1),
    }


def run_rate(
    envs: int, block_seconds: float, pairs: int, sim_hz: float, control_hz: float, seed: int, threads: int = 1
) -> dict:
    character, library = walk_run_setup(sim_hz, control_hz)
    config = SimConfig(sim_hz=sim_hz, control_hz=control_hz, threads=threads)
    sim = BatchedSim(character, library, envs, config, seed=seed)
    rng = np.random.default_rng(seed)

    def random_policy(state: np.ndarray) -> np.ndarray:
        return rng.normal(0.0, NOISE, (state.shape[0], sim.action_dim))

    out = {"sim_hz": sim_hz, "substeps": config.substeps}
    mlp = make_mlp_policy(sim.state_dim, sim.action_dim, seed)
    for key, policy in (("random_policy", random_policy), ("mlp_policy", mlp)):
        raw = RawStepper(character, library, config, seed)
        out[key] = interleaved(raw, BatchedRunner(sim, policy), pairs, block_seconds)
    out["bad_qacc_warnings"] = out["random_policy"]["bad_qacc_warnings"] + out["mlp_policy"]["bad_qacc_warnings"]
    return out


def run(
    envs: int,
    seconds: float,
    sim_hz: float | list[float],
    control_hz: float,
    seed: int = 0,
    block_seconds: float = 0.25,
    threads: int = 1,
) -> dict:
    """Each policy at each rate: `seconds` of interleaved blocks, `block_seconds` each."""
    import torch

    torch.set_num_threads(1)
    rates = [sim_hz] if isinstance(sim_hz, int | float) else list(sim_hz)
    pairs = max(3, int(round(seconds / (2 * block_seconds))))
    return {
        "benchmark": "sim",
        "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "versions": {"mujoco": mujoco.__version__, "torch": torch.__version__},
        "threads": threads,
        "envs": envs,
        "control_hz": control_hz,
        "block_seconds": block_seconds,
        "pairs": pairs,
        "rates": [run_rate(envs, block_seconds, pairs, hz, control_hz, seed, threads) for hz in rates],
    }


def format_table(r: dict) -> str:
    lines = [
        f"sim benchmark: {r['envs']} envs, control {r['control_hz']:g} Hz, {r['threads']} thread(s); per policy "
        f"{r['pairs']} pairs of {r['block_seconds']:g} s blocks, raw and batched interleaved",
        f"{'sim Hz':>7}{'K':>4}  {'policy':<11}{'raw phys/s':>12}{'batched phys/s':>16}{'control/s':>11}"
        f"{'ratio to raw':>14}{'ratio IQR':>15}{'bad qacc':>10}{'phys steps':>12}",
    ]
    for rate in r["rates"]:
        for key, label in (("random_policy", "random"), ("mlp_policy", "MLP 3x512")):
            x = rate[key]
            q1, q3 = x["ratio_quartiles"]
            lines.append(
                f"{rate['sim_hz']:>7g}{rate['substeps']:>4}  {label:<11}{x['raw_physics_steps_per_s']:>12,.0f}"
                f"{x['physics_steps_per_s']:>16,.0f}{x['control_steps_per_s']:>11,.0f}"
                f"{x['physics_step_ratio']:>14.3f}{f'{q1:.3f}-{q3:.3f}':>15}"
                f"{x['bad_qacc_warnings']:>10}{x['batched_physics_steps']:>12,}"
            )
    lines.append(
        "ratio: median over pairs of batched/raw physics steps per second; "
        "bad qacc: mjWARN_BADQACC during the batched blocks (over 'phys steps')"
    )
    return "\n".join(lines)
