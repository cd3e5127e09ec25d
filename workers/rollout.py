"""The rollout worker: M simulated characters driven by any policy, recording what its learners need.

One worker serves every method: it steps the batched simulator with the
`Policy` it is given (`workers.policies`: the VAE controller, the PPO
actor-critic, the experts, the task policies) and records, per control step and
environment, the body states before and after, the actions, the episode ends
with their cause, and what the policy and the recorders add:

- the policy's extras (PPO: observation, log-probability, value);
- for policies that act on an observation, the observation after the last step
  (`last_obs`) and the final observation of each truncated episode (`final_obs`,
  stored sparsely as rows t, env m), for bootstrapping;
- each `Recorder`'s arrays (`workers.recorders`): AMP's Φ(s_t), Φ(s_{t+1})
  (`AMPFeatures`), the imitation reward and its terms (`ImitationReward`),
  ControlVAE's tracking reward (`TrackingReward`).

Finished environments (fall, tracking failure, clip end, timeout) are reset at
once from the library's start distribution; `truncated` marks the ends that are
time limits (timeout, end of a one-shot clip), the others are terminal.

The policy runs on the simulator's device (`SimConfig.device`: the CPU, or the GPU of MuJoCo
Warp's worlds), with its noise drawn from the worker's CPU generator (`workers.policies`).

The worker owns its random streams (the simulator's resets, and the numpy and
torch streams it hands its policy), so the same seed and the same weights give
the same trajectories, and `state_dict` restores them together with the
environments' physical state.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from workers.body.character import Character
from workers.body.features import relative_position_error
from workers.learners.base import Weights
from workers.motion.library import MotionLibrary
from workers.policies import Policy
from workers.recorders import Recorder, to_host
from workers.sim.env import SimConfig, Simulator, StepResult, make_sim
from workers.types import Trajectory


class RolloutWorker:
    def __init__(
        self,
        character: Character,
        library: MotionLibrary,
        num_envs: int,
        policy: Policy,
        sim_config: SimConfig | None = None,
        seed: int = 0,
        worker_id: int = 0,
        recorders: Sequence[Recorder] = (),
        switch_rate: float = 0.0,
        switch_window: float = 2.0,
        sim: Simulator | None = None,
    ):
        if switch_rate < 0 or switch_window <= 0:
            raise ValueError(f"need switch_rate >= 0 and switch_window > 0, got {switch_rate} and {switch_window}")
        self.library = library
        self.worker_id = worker_id
        sim_seed, np_seed, torch_seed = np.random.SeedSequence([seed, worker_id]).generate_state(3)
        # `sim`: an already built simulator of num_envs environments (a benchmark's), instead of make_sim's.
        self.sim = sim if sim is not None else make_sim(character, library, num_envs, sim_config, seed=int(sim_seed))
        if self.sim.num_envs != num_envs:
            raise ValueError(f"the simulator has {self.sim.num_envs} environments, the worker was asked for {num_envs}")
        self.rng = np.random.default_rng(int(np_seed))
        self.generator = torch.Generator().manual_seed(int(torch_seed))
        self.policy = policy
        policy.bind(num_envs, self.rng, self.generator)
        # Inference runs where the simulator's worlds are (a GPU with MuJoCo Warp on CUDA, else the CPU).
        policy.to(self.sim.config.device)
        # A policy that records too (the task policy: its goals and rewards) records after the others, once: also
        # when it is among the recorders given (another worker's, which `bench host` passes on).
        self.recorders = list(recorders)
        if isinstance(policy, Recorder) and policy not in self.recorders:
            self.recorders.append(policy)
        # Counters for `stats`.
        self.steps_collected = 0
        self.episodes = 0
        self.episode_steps = 0  # summed length of the finished episodes
        self.ends = {"fell": 0, "tracking_failed": 0, "clip_ended": 0, "timeout": 0}
        self.collect_seconds = 0.0
        self.returns = np.zeros(num_envs)  # running sums of the recorded reward, when there is one
        self.finished_returns: list[float] = []
        # Clip switches (ControlVAE §3.4.4): per environment and control step with this probability, the
        # reference jumps to a start drawn like a reset's; a fall within `switch_window` seconds after a
        # switch counts against it, none for that long as a recovery.
        self.switch_probability = switch_rate / self.sim.config.control_hz
        self.switch_window_steps = max(int(round(switch_window * self.sim.config.control_hz)), 1)
        self.since_switch = np.full(num_envs, -1)  # control steps since the last switch; -1: none pending

    @property
    def num_envs(self) -> int:
        return self.sim.num_envs

    @property
    def version(self) -> int:
        return self.policy.version

    def set_weights(self, weights: Weights) -> None:
        """Load published weights into the policy and remember their version."""
        self.policy.set_weights(weights)

    def collect(self, steps: int) -> Trajectory:
        """Run every environment for `steps` control steps; the trajectory, tagged with the weights' version."""
        t0 = time.perf_counter()
        sim, m, policy = self.sim, self.num_envs, self.policy
        # Beside a simulator that computes on its device, the body states stay there (the policy reads them
        # there, or a host copy if it cannot); so do the actions of a policy that acts there (`Policy.act`), which
        # the simulator takes as they are. The trajectory's leave the device in one copy at the end.
        on_device = sim.computes_on_device
        bs = sim.device_body_states() if on_device else sim.body_states()
        shape = (steps, m, sim.character.num_bodies, 13)
        states = torch.empty(shape, device=bs.device) if on_device else np.empty(shape, np.float32)
        next_states = torch.empty_like(states) if on_device else np.empty_like(states)
        actions: np.ndarray | torch.Tensor | None = None  # made at the first step, where the policy's actions are
        done = np.empty((steps, m), bool)
        truncated = np.empty((steps, m), bool)
        switched = np.zeros((steps, m), bool)
        switch_counts = np.zeros(3, np.int64)  # switches, falls after one, recoveries
        clip_id = np.empty((steps, m), np.int64)
        frame = np.empty((steps, m), np.int64)
        extras: dict[str, np.ndarray] = {}
        final_rows: list[tuple[int, int]] = []
        final_obs: list[np.ndarray] = []
        for r in self.recorders:
            r.begin(steps, m, sim)
        for t in range(steps):
            states[t] = bs
            clip_id[t] = sim.clip_id
            frame[t] = sim.start_frame + sim.steps
            a, step_extras = policy.act(sim, self._for_policy(bs))
            if actions is None:
                actions = _rows_like(steps, a, float32=True)
            actions[t] = a
            for k, v in step_extras.items():
                if k not in extras:
                    extras[k] = _rows_like(steps, v)
                extras[k][t] = v
            result = sim.step(a)
            next_states[t] = result.on_device.body_states if on_device else result.body_states
            done[t] = result.done
            truncated[t] = result.timeout | result.clip_ended
            for r in self.recorders:
                r.record(t, sim, result)
            bs = next_states[t]
            if self.switch_probability > 0:
                self._follow_switches(result, switch_counts)
            if result.done.any():
                ids = np.flatnonzero(result.done)
                if policy.observes and truncated[t].any():
                    cut = np.flatnonzero(truncated[t])
                    final_rows.extend((t, int(i)) for i in cut)
                    final_obs.append(policy.observe(sim, self._for_policy(bs))[cut])
                self._count_ends(result, ids)
                sim.reset(ids)
                policy.episodes_reset(ids)
                if on_device:
                    bs = bs.clone()
                    rows = torch.as_tensor(ids, device=bs.device)
                    bs[rows] = sim.device_body_states()[rows]
                else:
                    bs = bs.copy()
                    bs[ids] = sim.body_states(ids)
                for r in self.recorders:
                    if hasattr(r, "after_reset"):
                        r.after_reset(sim, ids)
            if self.switch_probability > 0:
                switched[t] = self._switch(~result.done)
                switch_counts[0] += int(switched[t].sum())
        for r in self.recorders:
            extras.update(r.finish())
        extras = {k: to_host(v) for k, v in extras.items()}  # one copy
        extras["truncated"] = truncated
        if self.switch_probability > 0:
            extras["switched"] = switched
            extras.update(zip(("switches", "switch_falls", "switch_recoveries"), switch_counts, strict=True))
        if policy.observes:
            extras["last_obs"] = policy.observe(sim, self._for_policy(bs))
            extras["final_rows"] = np.asarray(final_rows, np.int64).reshape(-1, 2)
            width = extras["last_obs"].shape[-1]
            extras["final_obs"] = np.concatenate(final_obs) if final_obs else np.zeros((0, width), np.float32)
        if "reward" in extras:
            self._count_returns(extras["reward"], done)
        if actions is None:  # no steps
            actions = np.empty((0, m, sim.action_dim), np.float32)
        states, next_states, actions = map(to_host, (states, next_states, actions))
        self.steps_collected += steps * m
        self.collect_seconds += time.perf_counter() - t0
        return Trajectory(states, next_states, actions, done, clip_id, frame, self.version, self.worker_id, extras)

    def _for_policy(self, bs: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """Body states as the policy takes them: a device tensor as it is if the policy reads those, else NumPy."""
        if isinstance(bs, torch.Tensor) and not self.policy.reads_device_states:
            return bs.cpu().numpy()
        return bs

    def demonstrate(self, clip_ids: np.ndarray, max_steps: np.ndarray) -> list[dict[str, Any]]:
        """One episode per entry: clip `clip_ids[i]` tracked from its frame 0 for up to `max_steps[i]` control
        steps, ending early where the character falls (no reset, no tracking-failure end). Episodes run
        `num_envs` at a time. Each is {"states" [L+1, B, 13], "actions" [L, A], "clip", "fell",
        "tracking_error": mean body-position error relative to the root (m)}."""
        sim, m = self.sim, self.num_envs
        clip_ids, max_steps = np.asarray(clip_ids, int), np.asarray(max_steps, int)
        out: list[dict[str, Any]] = []
        for first in range(0, len(clip_ids), m):
            n = min(m, len(clip_ids) - first)
            clips = np.resize(clip_ids[first : first + n], m)  # spare environments repeat the jobs
            limit = np.resize(max_steps[first : first + n], m)
            ids = np.arange(m)
            sim.reset(ids, clips, np.zeros(m, int))
            self.policy.episodes_reset(ids)
            horizon = int(limit.max())
            states = np.empty((horizon + 1, m, sim.character.num_bodies, 13), np.float32)
            actions = np.empty((horizon, m, sim.action_dim), np.float32)
            length, fell, error = np.zeros(m, int), np.zeros(m, bool), np.zeros(m)
            bs = sim.body_states()
            states[0] = bs
            for t in range(horizon):
                running = ~fell & (t < limit)
                if not running.any():
                    break
                a, _ = self.policy.act(sim, bs)
                actions[t] = to_host(a)
                result = sim.step(a)
                bs = result.body_states
                states[t + 1] = bs
                err = relative_position_error(result.kin.xpos, sim.reference_state().xpos)
                length[running] += 1
                error[running] += err[running]
                fell |= running & result.fell
            for e in range(n):
                L = int(length[e])
                out.append(
                    {
                        "states": states[: L + 1, e].copy(),
                        "actions": actions[:L, e].copy(),
                        "clip": int(clips[e]),
                        "fell": bool(fell[e]),
                        "tracking_error": float(error[e] / max(L, 1)),
                    }
                )
            self.steps_collected += int(length.sum())
        return out

    def _switch(self, running: np.ndarray) -> np.ndarray:
        """Switch the reference of running environments at the switch rate; [M] which switched."""
        switch = running & (self.rng.random(self.num_envs) < self.switch_probability)
        ids = np.flatnonzero(switch)
        if len(ids):
            clips, frames = self.library.sample_starts(len(ids), self.rng)
            self.sim.switch_reference(ids, clips, frames)
            self.since_switch[ids] = 0
            for r in self.recorders:
                if hasattr(r, "after_switch"):
                    r.after_switch(self.sim, ids)
        return switch

    def _follow_switches(self, result: StepResult, counts: np.ndarray) -> None:
        """Count the falls (counts[1]) and recoveries (counts[2]) of the environments that switched lately."""
        pending = self.since_switch >= 0
        self.since_switch[pending] += 1
        fell = pending & result.fell
        recovered = pending & ~result.fell & (self.since_switch >= self.switch_window_steps)
        counts[1] += int(fell.sum())
        counts[2] += int(recovered.sum())
        self.since_switch[fell | recovered | result.done] = -1

    def _count_ends(self, result, ids: np.ndarray) -> None:
        self.episodes += len(ids)
        self.episode_steps += int(self.sim.steps[ids].sum())
        for key in self.ends:
            if key != "fell" or result.end_on_fall:
                self.ends[key] += int(getattr(result, key)[ids].sum())

    def _count_returns(self, reward: np.ndarray, done: np.ndarray) -> None:
        for t in range(reward.shape[0]):
            self.returns += reward[t]
            ids = np.flatnonzero(done[t])
            self.finished_returns.extend(self.returns[ids].tolist())
            self.returns[ids] = 0.0

    def stats(self) -> dict[str, float]:
        """Totals since the worker was built: steps, finished episodes and why they ended, throughput.

        `episode_return` is the mean undiscounted return of the episodes finished since the
        last call (NaN if none), when the worker records a reward.
        """
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
        if self.finished_returns:
            out["episode_return"] = float(np.mean(self.finished_returns))
            self.finished_returns = []
        return out

    # Checkpoints -----------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """RNG states, counters, the policy's episode state and the environments' state: NumPy and plain types.

        The weights are not included (the learner publishes them); restoring into a worker with the
        same weights continues the same trajectories.
        """
        sim = self.sim
        return {
            "version": self.version,
            "rng": self.rng.bit_generator.state,
            "sim_rng": sim.rng.bit_generator.state,
            "generator": self.generator.get_state().numpy().copy(),
            "policy": self.policy.state_dict(),
            "returns": self.returns.copy(),
            "since_switch": self.since_switch.copy(),
            "counters": {
                "steps_collected": self.steps_collected,
                "episodes": self.episodes,
                "episode_steps": self.episode_steps,
                "collect_seconds": self.collect_seconds,
                **{f"ends.{k}": v for k, v in self.ends.items()},
            },
            "envs": sim.save_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        sim = self.sim
        envs = state["envs"]
        if len(envs["clip_id"]) != self.num_envs:
            raise ValueError(
                f"worker state is for {len(envs['clip_id'])} environments, this worker has {self.num_envs}"
            )
        self.policy.version = int(state["version"])
        self.rng.bit_generator.state = state["rng"]
        sim.rng.bit_generator.state = state["sim_rng"]
        self.generator.set_state(torch.from_numpy(np.asarray(state["generator"], np.uint8).copy()))
        self.policy.load_state_dict(state["policy"])
        self.returns = np.asarray(state["returns"], float).copy()
        self.since_switch = np.asarray(state.get("since_switch", np.full(self.num_envs, -1)), int).copy()
        c = state["counters"]
        self.steps_collected = int(c["steps_collected"])
        self.episodes = int(c["episodes"])
        self.episode_steps = int(c["episode_steps"])
        self.collect_seconds = float(c["collect_seconds"])
        self.ends = {k: int(c[f"ends.{k}"]) for k in self.ends}
        sim.restore_state(envs)  # physics, warm start and reference bookkeeping


def _rows_like(steps: int, v: np.ndarray | torch.Tensor, float32: bool = False) -> np.ndarray | torch.Tensor:
    """An empty array of `steps` rows shaped like v, where v is (a tensor on v's device, or NumPy), of v's
    dtype or float32."""
    if isinstance(v, torch.Tensor):
        return torch.empty((steps, *v.shape), dtype=torch.float32 if float32 else v.dtype, device=v.device)
    return np.empty((steps, *np.shape(v)), np.float32 if float32 else np.asarray(v).dtype)
