"""What every simulator backend shares: the config, the step's result, and the reference bookkeeping.

`Simulator` is the interface the rollout worker, the evaluations and the policies use: N
environments of the humanoid stepped together, each following a reference (clip, frame) of
the motion library. Everything here is backend-independent NumPy over the batch: resets to
reference states drawn from the library (reference state initialisation), the step count,
clip switches, the terminations (tracking failure from the head error, clip ends, time
limits; falls come from the backend's contacts), the `StepResult`, the reference's states and
features one step ahead, the simulated bodies as a `KinState`, and saving and restoring the
environments' state.

A backend subclasses it and fills in the physics through a few hooks:

- `_build_physics()`: make the N worlds of `self.model` (called once, before the first reset);
- `_set_physics_state(env_ids, qpos, qvel, ctrl)`: put those environments into that state, with
  zero time and solver warm start, and compute the positions and contacts of the new state;
- `_advance(actions)`: apply the PD targets [N, A] (float64; a backend that computes on its device also
  takes a tensor) and advance K = `substeps` physics
  steps, after which the positions, velocities and contacts of the new state are known;
- `_arrays()`: the current `PhysicsArrays` (qpos, qvel, xpos, xquat, cvel, subtree_com; float64);
- `_contact_falls()`: [N] whether a contact of the current state involves a geom of
  `self._fall_geom` (anything but the ground and the allowed geoms);
- `qacc_warmstart`, `_set_warmstart(values)`, `warning_counts(warning)`, `get_data(i)`.

The backends are `workers.sim.env.BatchedSim` (MuJoCo C) and `workers.sim.warp_sim.WarpSim`
(MuJoCo Warp); `workers.sim.env.make_sim` builds the one `SimConfig.backend` names.
"""

from __future__ import annotations

import abc
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, NamedTuple

import mujoco
import numpy as np
import torch

from workers.body.character import Character
from workers.body.features import state_features
from workers.models.body_state import pack
from workers.models.device_features import DeviceReference, DeviceState
from workers.models.tracking_goal import check as check_goal
from workers.models.tracking_goal import mimic_goal
from workers.motion.library import MotionLibrary
from workers.sim.terrain import TerrainConfig, ground_geoms, reset_lift, terrain_model
from workers.types import KinState

BACKENDS = ("mujoco", "warp")
_DEVICE = re.compile(r"cpu|cuda(:\d+)?")
_YZX, _ZXY = [1, 2, 0], [2, 0, 1]  # component orders of a cross product
# The keys of `Simulator.save_state` (and of the rollout worker's checkpoints, which store it).
STATE_KEYS = ("qpos", "qvel", "qacc_warmstart", "clip_id", "start_frame", "steps", "bad_head_steps")


@dataclass
class SimConfig:
    """Rates and termination rules of the batched simulator."""

    # Physics rate. 480 Hz is PhysicsVAE's; see docs in the README for the stability measurement.
    sim_hz: float = 480.0
    # Policy rate; sim_hz must be a whole multiple of it.
    control_hz: float = 30.0
    # Bodies allowed to touch the ground; any other contact is a fall. Empty: never fall on contact.
    allowed_contacts: tuple[str, ...] = ("right_ankle", "left_ankle")
    # Whether a fall ends the episode; false (ControlVAE's collection) still reports it in StepResult.fell.
    end_on_fall: bool = True
    # Head error (metres) that, held for tracking_error_s seconds, ends an episode. 0 disables.
    tracking_error_m: float = 0.5
    tracking_error_s: float = 1.0
    # Episode length cap in control steps; 0 means none.
    max_episode_steps: int = 0
    # Threads that step the environments (the caller's included; MuJoCo C only). 1 by default: rollout
    # workers share the machine's cores, and results are bit-identical at any thread count.
    threads: int = 1
    # The ground: flat (the character file's floor) or a rough height field (`workers.sim.terrain`; MuJoCo C only).
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    # Physics: "mujoco" (MuJoCo C, `workers.sim.env.BatchedSim`) or "warp" (MuJoCo Warp,
    # `workers.sim.warp_sim.WarpSim`; needs the warp extra). `workers.sim.env.make_sim` builds the one named here.
    backend: str = "mujoco"
    # Where the warp backend's worlds live: "cpu" (Warp's CPU device), "cuda" or "cuda:N". MuJoCo C runs on
    # the CPU only, so the mujoco backend takes "cpu" only.
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"sim backend must be one of {BACKENDS}, got {self.backend!r}")
        if not isinstance(self.device, str) or not _DEVICE.fullmatch(self.device):
            raise ValueError(f"sim device must be 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")
        if self.backend == "mujoco" and self.device != "cpu":
            raise ValueError(f"sim device {self.device!r} needs sim backend 'warp': MuJoCo C runs on the CPU")
        if self.backend == "warp":
            from workers.sim.warp_physics import INSTALL_HINT, WarpUnavailable, warp_available

            if not warp_available():
                raise WarpUnavailable(f"sim backend 'warp' needs mujoco-warp and warp-lang: {INSTALL_HINT}")

    @property
    def substeps(self) -> int:
        ratio = self.sim_hz / self.control_hz
        if self.control_hz <= 0 or ratio < 1 or abs(ratio - round(ratio)) > 1e-6:
            raise ValueError(
                f"sim_hz ({self.sim_hz}) must be a positive whole multiple of control_hz ({self.control_hz})"
            )
        return int(round(ratio))


def without_tracking_termination(config: SimConfig | None = None, keep_time_limit: bool = False) -> SimConfig:
    """`config` (default `SimConfig()`) with no end on tracking failure (`tracking_error_m` = 0) and,
    unless `keep_time_limit`, no episode cap (`max_episode_steps` = 0).

    For runs that do not hold the character to its reference: the evaluations, which run each
    episode for their own number of steps, and AMP, whose policy imitates a style, not the clip."""
    config = config or SimConfig()
    time_limit = config.max_episode_steps if keep_time_limit else 0
    return replace(config, tracking_error_m=0.0, max_episode_steps=time_limit)


@dataclass
class StepResult:
    """What one control step returns; arrays have N rows. `state` is computed when first read."""

    ref_state: np.ndarray  # [N, D] s of the reference at the same time
    # The raw simulated state (`kin`), or what makes it when first read (MuJoCo Warp: host copies of the device's).
    # The reference's is Simulator.reference_state().
    kin_source: KinState | Callable[[], KinState]
    fell: np.ndarray  # [N] bool
    tracking_failed: np.ndarray  # [N] bool
    clip_ended: np.ndarray  # [N] bool
    timeout: np.ndarray  # [N] bool
    end_on_fall: bool = True  # whether `fell` ends the episode
    # What a backend computed where its state lives (MuJoCo Warp: on the device); None: derived from `kin` here.
    packed: np.ndarray | Callable[[], np.ndarray] | None = field(default=None, repr=False)  # [N, B, 13] float32
    features: Callable[[], np.ndarray] | None = field(default=None, repr=False)  # s [N, D], called when read
    on_device: DeviceState | None = field(default=None, repr=False)  # the new state where the worlds are
    done: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.done = self.tracking_failed | self.clip_ended | self.timeout
        if self.end_on_fall:
            self.done = self.done | self.fell

    @cached_property
    def kin(self) -> KinState:
        """The simulated state as a `KinState` (float64 arrays; made when first read, then the same)."""
        return self.kin_source if isinstance(self.kin_source, KinState) else self.kin_source()

    @cached_property
    def state(self) -> np.ndarray:
        """[N, D] s of the simulated characters (from `kin`, or the backend's `features`; the same whenever read).

        Lazy because most callers observe through the policy's own features, and computing
        s for every step cost ~4% of a rollout worker's control step at 8 environments."""
        return self.features() if self.features is not None else state_features(self.kin)

    @cached_property
    def body_states(self) -> np.ndarray:
        """[N, B, 13] float32 body states of the simulated characters (`pack(kin)`, or the backend's)."""
        if self.packed is None:
            return pack(self.kin)
        return self.packed() if callable(self.packed) else self.packed


class PhysicsArrays(NamedTuple):
    """A backend's current physics arrays, float64, world body included (`_arrays`); views or copies."""

    qpos: np.ndarray  # [N, nq]
    qvel: np.ndarray  # [N, nv]
    xpos: np.ndarray  # [N, nbody, 3]
    xquat: np.ndarray  # [N, nbody, 4]
    cvel: np.ndarray  # [N, nbody, 6] com-based velocity (rot:lin)
    subtree_com: np.ndarray  # [N, nbody, 3]


class Simulator(abc.ABC):
    """N environments of `character` following references of `library`; the physics is a subclass's.

    Args:
      character, library: the humanoid and the motion library (sampled at `config.control_hz`).
      num_envs: environments stepped together.
      config: rates, terminations, terrain and backend (default `SimConfig(backend=<the class's>)`);
        its backend must be the class's (`workers.sim.env.make_sim` chooses the class).
      seed: of the reset stream `rng` (starts drawn from the library).
    """

    backend = ""  # the SimConfig.backend a subclass implements
    # Whether the state lives on `config.device` and what reads it is best computed there (MuJoCo Warp): the
    # policies then make their observations on their device (`workers.policies.observe_on`), in torch.
    computes_on_device = False

    def __init__(
        self,
        character: Character,
        library: MotionLibrary,
        num_envs: int,
        config: SimConfig | None = None,
        seed: int = 0,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        self.character = character
        self.library = library
        self.config = config or SimConfig(backend=self.backend)
        if self.config.backend != self.backend:
            raise ValueError(
                f"{type(self).__name__} runs sim backend {self.backend!r}, the config says "
                f"{self.config.backend!r} (workers.sim.env.make_sim builds the backend a config names)"
            )
        self._check_config()
        self.substeps = self.config.substeps
        self._rough = self.config.terrain.kind == "rough"
        if self._rough and character.root_dofs == 0:
            raise ValueError("rough terrain needs a character with a free root (fixed_root=False)")
        # Rough: the character's model with the height field, compiled anew (Character.model is untouched).
        self.model = terrain_model(character.spec(), self.config.terrain) if self._rough else character.model
        self.model.opt.timestep = 1.0 / self.config.sim_hz
        lib_dt = float(np.mean(library.dt))
        if abs(lib_dt * self.config.control_hz - 1.0) > 0.02:
            raise ValueError(
                f"library sampled at {1 / lib_dt:.2f} Hz, simulator controls at {self.config.control_hz} Hz"
            )
        self.num_envs = num_envs
        self.rng = np.random.default_rng(seed)
        self._fell = np.zeros(num_envs, bool)
        self.clip_id = np.zeros(num_envs, int)
        self.start_frame = np.zeros(num_envs, int)
        self.steps = np.zeros(num_envs, int)
        self._bad_head_steps = np.zeros(num_envs, int)
        allowed = [self.model.geom(n).id for n in self.config.allowed_contacts] + ground_geoms(self.model)
        self._fall_geom = np.ones(self.model.ngeom, bool)  # lookup: does touching this geom end the episode
        self._fall_geom[allowed] = False
        self._fall_on_contact = len(self.config.allowed_contacts) > 0
        self._head_limit_steps = int(np.ceil(self.config.tracking_error_s * self.config.control_hz))
        self._build_physics()
        self.reset()

    def _check_config(self) -> None:
        """Refuse what the backend cannot run (before the model is built)."""
        if self.config.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.config.threads}")

    # Sizes -----------------------------------------------------------------
    @property
    def action_dim(self) -> int:
        return self.character.num_actions

    @property
    def state_dim(self) -> int:
        return 16 * self.character.num_bodies + 3

    # Reset -----------------------------------------------------------------
    def reset(
        self,
        env_ids: np.ndarray | None = None,
        clip_ids: np.ndarray | None = None,
        frames: np.ndarray | None = None,
    ) -> np.ndarray:
        """Reference state initialisation; states s [len(env_ids), D] of the reset environments.

        Without clip_ids/frames the start is drawn from the library's start weights.
        """
        env_ids = np.arange(self.num_envs) if env_ids is None else np.asarray(env_ids, dtype=int)
        if len(env_ids) == 0:
            return np.zeros((0, self.state_dim), np.float32)
        if clip_ids is None or frames is None:
            clip_ids, frames = self.library.sample_starts(len(env_ids), self.rng)
        ref = self.library.state(clip_ids, frames)
        qpos = ref.qpos
        if self._rough:
            # The reference was recorded on flat ground: raise each character just clear of the bumps.
            qpos = qpos.copy()
            qpos[:, 2] += reset_lift(self.config.terrain, self.model, ref.xpos, ref.xquat)
        self.set_state(env_ids, qpos, ref.qvel)
        self.clip_id[env_ids] = clip_ids
        self.start_frame[env_ids] = frames
        self.steps[env_ids] = 0
        self._bad_head_steps[env_ids] = 0
        if self._rough:  # raised: the precomputed s has the reference's heights
            return state_features(self.kin_state()[env_ids])
        # The environments now hold the reference state (exactly, in float64), whose s is precomputed.
        return self.library.features(clip_ids, frames)

    def set_state(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Put environments into the given generalised state (positions and contacts computed), their
        controls at the PD targets of qpos, their time and the solver's warm start zero."""
        env_ids = np.asarray(env_ids, dtype=int)
        if len(env_ids) == 0:
            return
        self._set_physics_state(env_ids, qpos, qvel, self.character.qpos_to_action(np.asarray(qpos)))

    # Step ------------------------------------------------------------------
    def step(self, actions: np.ndarray | torch.Tensor) -> StepResult:
        """Apply PD targets [N, 28] for one control step: NumPy, or a tensor (a backend that computes on its
        device takes it there as it is, so a policy's actions on that device do not cross to the host)."""
        if isinstance(actions, torch.Tensor) and not self.computes_on_device:
            actions = actions.detach().cpu().numpy()
        if not isinstance(actions, torch.Tensor):
            actions = np.asarray(actions, dtype=np.float64)
        if tuple(actions.shape) != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must be [{self.num_envs}, {self.action_dim}], got {list(actions.shape)}")
        self._advance(actions)
        self.steps += 1
        observed = self._observe()
        head_pos = observed.pop("head_xpos")
        frames = self.start_frame + self.steps
        if self.config.tracking_error_m > 0:
            head = self.character.head_body
            ref_head = self.library.body_positions(self.clip_id, frames, head)
            bad = np.linalg.norm(head_pos - ref_head, axis=-1) > self.config.tracking_error_m
            self._bad_head_steps = np.where(bad, self._bad_head_steps + 1, 0)
            tracking_failed = self._bad_head_steps >= self._head_limit_steps
        else:
            tracking_failed = np.zeros(self.num_envs, bool)
        clip_ended = self.library.is_last_frame(self.clip_id, frames)
        cap = self.config.max_episode_steps
        timeout = self.steps >= cap if cap > 0 else np.zeros(self.num_envs, bool)
        self._fell = self._contact_falls() if self._fall_on_contact else np.zeros(self.num_envs, bool)
        return StepResult(
            ref_state=self.library.features(self.clip_id, frames),
            fell=self._fell.copy(),
            tracking_failed=tracking_failed,
            clip_ended=clip_ended,
            timeout=timeout,
            end_on_fall=self.config.end_on_fall,
            **observed,
        )

    def switch_reference(self, env_ids: np.ndarray, clip_ids: np.ndarray, frames: np.ndarray) -> None:
        """Give environments a new reference (clip, frame) without touching their bodies (ControlVAE's
        trajectory sampler, §3.4.4): the episode goes on, its step count too, and the head-error count
        starts over. `start_frame` becomes the offset that puts `start_frame + steps` on `frames`."""
        env_ids = np.asarray(env_ids, dtype=int)
        self.clip_id[env_ids] = clip_ids
        self.start_frame[env_ids] = np.asarray(frames, int) - self.steps[env_ids]
        self._bad_head_steps[env_ids] = 0

    # State access ----------------------------------------------------------
    def kin_state(self) -> KinState:
        """The simulated state of all environments (copies, float64)."""
        a = self._arrays()
        xpos = a.xpos[:, 1:]
        cvel = a.cvel[:, 1:]
        w = cvel[..., :3]
        # cvel's linear part is at the root's subtree centre of mass; moved to each body's origin:
        # v + w x r. The cross product is written out (same products and order as np.cross,
        # so the same bits) because np.cross costs several times more NumPy calls.
        r = xpos - a.subtree_com[:, 1, None, :]
        lin = cvel[..., 3:] + (w[..., _YZX] * r[..., _ZXY] - w[..., _ZXY] * r[..., _YZX])
        return KinState(a.qpos.copy(), a.qvel.copy(), xpos.copy(), a.xquat[:, 1:].copy(), lin, w.copy())

    def body_states(self, env_ids: np.ndarray | None = None) -> np.ndarray:
        """The body states [N, B, 13] (float32, `workers.models.body_state.pack`) of the simulated characters
        (rows `env_ids` only, when given): what a trajectory stores and a policy reads."""
        kin = self.kin_state()
        return pack(kin if env_ids is None else kin[env_ids])

    def device_reference(self) -> DeviceReference | None:
        """The motion library's frames on `config.device` (`DeviceReference`), where the backend computes there;
        None here."""
        return None

    @property
    def torch_device(self) -> torch.device:
        """Where the state's tensors live: the CPU here, the device of MuJoCo Warp's worlds there."""
        return torch.device("cpu")

    def device_body_states(self) -> torch.Tensor:
        """[N, B, 13] float32 body states on `config.device` (a torch tensor), where the backend computes there."""
        raise NotImplementedError(f"{type(self).__name__} keeps its state on the host: use body_states()")

    def device_state(self) -> DeviceState | None:
        """The current state on `config.device` as torch tensors, where the backend keeps it there
        (`computes_on_device`); None here."""
        return None

    def _observe(self) -> dict[str, Any]:
        """What a control step reports of the new state, as `StepResult` fields: its `kin_source`, and what the
        backend computed itself (`packed`, `features`, `on_device`), and `head_xpos` [N, 3] (float64), the head's
        position the tracking-failure test reads; here the `KinState` and its head."""
        kin = self.kin_state()
        return {"kin_source": kin, "head_xpos": kin.xpos[:, self.character.head_body]}

    def reference_state(self) -> KinState:
        """The reference state at each environment's current time."""
        return self.library.state(self.clip_id, self.start_frame + self.steps)

    def reference_next_features(self, env_ids: np.ndarray | None = None) -> np.ndarray:
        """s̃_{t+1} [N, D] (rows `env_ids` only, when given): the reference's state features one control
        step after each environment's current time, as the library stores them (what a tracking policy
        observes and the VAE's posterior reads)."""
        ids = slice(None) if env_ids is None else env_ids
        return self.library.features(self.clip_id[ids], self.start_frame[ids] + self.steps[ids] + 1)

    def reference_next_body_states(self, env_ids: np.ndarray | None = None) -> np.ndarray:
        """The reference's body states [N, B, 13] (float32, `workers.models.body_state.pack`) one control step
        after each environment's current time (rows `env_ids` only, when given)."""
        ids = slice(None) if env_ids is None else env_ids
        return pack(self.library.state(self.clip_id[ids], self.start_frame[ids] + self.steps[ids] + 1))

    def tracking_goal(self, kind: str, bs: np.ndarray | torch.Tensor) -> torch.Tensor:
        """The tracking goal [N, G] (float32, `workers.models.tracking_goal`'s `kind`) of the environments in body
        states bs [N, B, 13], toward each one's reference one control step ahead; on the device beside a simulator
        that computes there (`computes_on_device`), else on the CPU (or where bs is, when it is a tensor)."""
        check_goal(kind)
        if self.computes_on_device:  # the reference looked up where the state is, the goal made there
            ref, clips, frames = self.device_reference(), self.clip_id, self.start_frame + self.steps + 1
            if kind == "reference":
                return ref.frame_features(clips, frames)
            b = torch.as_tensor(bs, dtype=torch.float32).to(ref.device)
            return mimic_goal(b, ref.state(clips, frames).body_states)
        if kind == "reference":
            return torch.from_numpy(self.reference_next_features().astype(np.float32))
        b = torch.as_tensor(bs, dtype=torch.float32)
        return mimic_goal(b, torch.from_numpy(self.reference_next_body_states()).to(b.device))

    # Saving and restoring ----------------------------------------------------
    def save_state(self) -> dict[str, np.ndarray]:
        """Every environment's state (NumPy copies under `STATE_KEYS`): physics (qpos, qvel, the solver's
        warm start) and reference bookkeeping (clip, start frame, steps, head-error count).

        `restore_state` of it, with the same actions, continues the same trajectories (on MuJoCo C
        bit for bit; on MuJoCo Warp from the same float32 state)."""
        a = self._arrays()
        return {
            "qpos": a.qpos.copy(),
            "qvel": a.qvel.copy(),
            "qacc_warmstart": np.array(self.qacc_warmstart, copy=True),
            "clip_id": self.clip_id.copy(),
            "start_frame": self.start_frame.copy(),
            "steps": self.steps.copy(),
            "bad_head_steps": self._bad_head_steps.copy(),
        }

    def restore_state(self, state: dict[str, Any]) -> None:
        """Put every environment back into a `save_state` (arrays with num_envs rows)."""
        if len(state["clip_id"]) != self.num_envs:
            raise ValueError(f"sim state is for {len(state['clip_id'])} environments, this one has {self.num_envs}")
        self.set_state(np.arange(self.num_envs), state["qpos"], state["qvel"])
        self._set_warmstart(state["qacc_warmstart"])  # set_state zeroes the warm start; the next step reads it
        self.clip_id[:] = state["clip_id"]
        self.start_frame[:] = state["start_frame"]
        self.steps[:] = state["steps"]
        self._bad_head_steps[:] = state["bad_head_steps"]

    # Hooks -----------------------------------------------------------------
    @abc.abstractmethod
    def _build_physics(self) -> None:
        """Make the num_envs worlds of `self.model` (once, before the first reset)."""

    @abc.abstractmethod
    def _set_physics_state(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray) -> None:
        """Put environments `env_ids` into (qpos, qvel) with controls `ctrl`, zero time and warm start, and
        compute the position and velocity stages (contacts included) of the new state."""

    @abc.abstractmethod
    def _advance(self, actions: np.ndarray) -> None:
        """Set the controls to `actions` [N, A] (float64) and advance every environment by `substeps` physics
        steps; afterwards the positions, velocities and contacts of the new state are known."""

    @abc.abstractmethod
    def _arrays(self) -> PhysicsArrays:
        """The current physics arrays of all environments."""

    @abc.abstractmethod
    def _contact_falls(self) -> np.ndarray:
        """[N] whether a contact of the current state involves a geom that `self._fall_geom` marks."""

    @abc.abstractmethod
    def _set_warmstart(self, values: np.ndarray) -> None:
        """Set the solver's warm start [N, nv] of every environment."""

    @property
    @abc.abstractmethod
    def qacc_warmstart(self) -> np.ndarray:
        """[N, nv] the solver's warm start of each environment (the next step's first guess of qacc)."""

    @abc.abstractmethod
    def warning_counts(self, warning: mujoco.mjtWarning = mujoco.mjtWarning.mjWARN_BADQACC) -> np.ndarray:
        """[N] how often each environment raised this MuJoCo warning since the simulator was made."""

    @abc.abstractmethod
    def get_data(self, i: int) -> mujoco.MjData:
        """A copy of environment i's whole MjData (for rendering or any mj_ function)."""
