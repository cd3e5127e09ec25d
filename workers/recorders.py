"""What a rollout worker records beyond states and actions: one `Recorder` per quantity a learner needs.

The rollout worker (`workers.rollout`) calls each recorder at the start of a
collect (`begin`), after every control step (`record`), after resets and clip
switches of some environments (`after_reset`, `after_switch`, where defined) and
at the end (`finish`), whose arrays [T, M, ...] go into the trajectory's extras.

- `AMPFeatures`: AMP's discriminator observation Φ(s_t), Φ(s_{t+1}) (AMP §5.3).
- `ImitationReward`: the tracking expert's DeepMimic-style reward and its terms
  (`workers.rewards`).
- `TrackingReward`: ControlVAE's Eq. 20 reward of each collected state against its
  reference (`workers.rewards.tracking_reward`), which data balancing reads (`workers.replay.balancing`).

Beside a simulator that computes on its device (MuJoCo Warp: `Simulator.computes_on_device`) they
compute there, in torch (`workers.models.device_features`), into arrays on the device that `finish`
copies to the host once; beside MuJoCo C, in NumPy.
"""

from __future__ import annotations

import numpy as np
import torch

from workers.body.character import Character
from workers.body.features import amp_dim, amp_features, state_features
from workers.models import body_state, device_features
from workers.models.device_features import DeviceState
from workers.rewards import DEFAULT_WEIGHTS, IMITATION_TERMS, imitation_reward, tracking_reward
from workers.sim.env import Simulator, StepResult
from workers.types import KinState


class Recorder:
    """Records arrays [T, M, ...] alongside the trajectory, from each step's result."""

    def begin(self, steps: int, num_envs: int, sim: Simulator) -> None:
        raise NotImplementedError

    def record(self, t: int, sim: Simulator, result: StepResult) -> None:
        raise NotImplementedError

    def finish(self) -> dict[str, np.ndarray]:
        raise NotImplementedError


def record_buffer(shape: tuple[int, ...], sim: Simulator) -> np.ndarray | torch.Tensor:
    """A float32 array for a collect's records: on the simulator's device beside one that computes there (copied
    to the host once, by `to_host`, at `finish`), else NumPy."""
    if sim.computes_on_device:
        return torch.empty(shape, device=sim.torch_device)
    return np.empty(shape, np.float32)


def to_host(values: np.ndarray | torch.Tensor) -> np.ndarray:
    """values as NumPy on the host (a tensor copied from its device)."""
    return values.cpu().numpy() if isinstance(values, torch.Tensor) else values


class AMPFeatures(Recorder):
    """AMP's discriminator observation of each transition: Φ(s_t) and Φ(s_{t+1}), [T, M, amp_dim] each."""

    def __init__(self, character: Character):
        self.character = character

    def begin(self, steps: int, num_envs: int, sim: Simulator) -> None:
        self.before = record_buffer((steps, num_envs, amp_dim(self.character)), sim)
        self.after = record_buffer(tuple(self.before.shape), sim)
        self.current = self._of(sim.device_state()) if sim.computes_on_device else self._of_kin(sim.kin_state())

    def _of(self, state: DeviceState) -> torch.Tensor:
        """Φ(s) computed where the state is (`workers.models.device_features`)."""
        return device_features.amp_features(self.character, state)

    def _of_kin(self, kin: KinState) -> np.ndarray:
        return amp_features(self.character, kin)

    def record(self, t: int, sim: Simulator, result: StepResult) -> None:
        self.before[t] = self.current
        on_device = result.on_device
        self.after[t] = self._of(on_device) if on_device is not None else self._of_kin(result.kin)
        self.current = self.after[t]

    def after_reset(self, sim: Simulator, ids: np.ndarray) -> None:
        if sim.computes_on_device:
            self.current = self.current.clone()
            rows = torch.as_tensor(ids, device=self.current.device)
            self.current[rows] = self._of(sim.device_state().rows(rows))
        else:
            self.current = self.current.copy()
            self.current[ids] = self._of_kin(sim.kin_state()[ids])

    def finish(self) -> dict[str, np.ndarray]:
        return {"amp_obs": to_host(self.before), "amp_next_obs": to_host(self.after)}


class ImitationReward(Recorder):
    """The tracking expert's reward r_t [T, M] (`workers.rewards`) and its terms, `reward/<term>` [T, M]."""

    def __init__(self, character: Character, weights: dict[str, float] | None = None):
        self.character = character
        self.weights = dict(DEFAULT_WEIGHTS if weights is None else weights)

    def begin(self, steps: int, num_envs: int, sim: Simulator) -> None:
        self.reward = record_buffer((steps, num_envs), sim)
        self.terms = {k: record_buffer((steps, num_envs), sim) for k in IMITATION_TERMS}

    def record(self, t: int, sim: Simulator, result: StepResult) -> None:
        if result.on_device is not None:  # where the state is, against the reference looked up there
            ref = sim.device_reference().state(sim.clip_id, sim.start_frame + sim.steps)
            r, terms = device_features.imitation_reward(self.character, result.on_device, ref, self.weights)
        else:
            r, terms = imitation_reward(self.character, result.kin, sim.reference_state(), self.weights)
        self.reward[t] = r
        for k, v in terms.items():
            self.terms[k][t] = v

    def finish(self) -> dict[str, np.ndarray]:
        return {"reward": to_host(self.reward), **{f"reward/{k}": to_host(v) for k, v in self.terms.items()}}


class TrackingReward(Recorder):
    """r_t of Eq. 20 for the state *before* each step (the state stored with transition t), [T, M].

    The state after a reset is the reference itself (r = 1 up to rounding); it is computed all the same.
    """

    def __init__(self, weights: np.ndarray, temperature: float = 20.0):
        self.weights = np.asarray(weights, np.float64)
        self.temperature = temperature

    def _of(self, sim: Simulator, ids: np.ndarray | None = None) -> np.ndarray | torch.Tensor:
        """The reward of environments `ids` (all by default) in their current state against their current
        reference frames; on the device beside a simulator that computes there."""
        rows = slice(None) if ids is None else ids
        clips, frames = sim.clip_id[rows], (sim.start_frame + sim.steps)[rows]
        if sim.computes_on_device:
            state = sim.device_state()
            state = state if ids is None else state.rows(ids)
            return self._on_device(sim, body_state.features(state.body_states), clips, frames)
        state = state_features(sim.kin_state())[rows]
        return tracking_reward(state, sim.library.features(clips, frames), self.weights, self.temperature)

    def _on_device(self, sim: Simulator, state: torch.Tensor, clips: np.ndarray, frames: np.ndarray) -> torch.Tensor:
        """Eq. 20 computed where the state is, from s there and the reference's s looked up there."""
        ref = sim.device_reference().frame_features(clips, frames)
        weights = torch.as_tensor(self.weights, dtype=torch.float32, device=state.device)
        return device_features.tracking_reward(state, ref, weights, self.temperature)

    def begin(self, steps: int, num_envs: int, sim: Simulator) -> None:
        self.reward = record_buffer((steps, num_envs), sim)
        self.current = self._of(sim)

    def record(self, t: int, sim: Simulator, result: StepResult) -> None:
        self.reward[t] = self.current
        if result.on_device is not None:
            s = body_state.features(result.on_device.body_states)
            self.current = self._on_device(sim, s, sim.clip_id, sim.start_frame + sim.steps)
        else:
            self.current = tracking_reward(result.state, result.ref_state, self.weights, self.temperature)

    def after_reset(self, sim: Simulator, ids: np.ndarray) -> None:
        if isinstance(self.current, torch.Tensor):
            self.current[torch.as_tensor(ids, device=self.current.device)] = self._of(sim, ids)
        else:
            self.current[ids] = self._of(sim, ids)

    after_switch = after_reset  # the same state against its new reference

    def finish(self) -> dict[str, np.ndarray]:
        return {"reward": to_host(self.reward)}
