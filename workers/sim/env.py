"""The batched simulator: N environments of the humanoid stepped together.

Each environment is its own `MjData` on one shared `MjModel`. A control step
applies the PD targets [N, 28] and advances every environment by
sim_hz / control_hz physics steps, then gathers positions, rotations and
velocities of all bodies of all environments into arrays, from which the state
features are computed in bulk.

Per environment a control step is `mj_step2` (finish the step whose position and
velocity stages are already computed, now with the new controls), `mj_step` for
the remaining substeps, then `mj_step1` so that body positions, velocities and
contacts of the new state are computed: exactly K physics steps in three calls,
with no separate `mj_forward`.

Reset is reference state initialisation from the motion library. Termination:
`fell` (a body other than the allowed ones, the feet by default, touches the
ground), `tracking_failed` (head further than `tracking_error_m` from the
reference's for `tracking_error_s`), `clip_ended` (a one-shot clip ran out) and
`timeout` (`max_episode_steps`). The caller resets finished environments.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from workers.motion.library import MotionLibrary
from workers.sim.character import Character
from workers.sim.features import state_features
from workers.types import KinState


@dataclass
class SimConfig:
    """Rates and termination rules of the batched simulator."""

    # Physics rate. 480 Hz is PhysicsVAE's; see docs in the README for the stability measurement.
    sim_hz: float = 480.0
    # Policy rate; sim_hz must be a whole multiple of it.
    control_hz: float = 30.0
    # Bodies allowed to touch the ground; any other contact is a fall. Empty: never fall on contact.
    allowed_contacts: tuple[str, ...] = ("right_ankle", "left_ankle")
    # Head error (metres) that, held for tracking_error_s seconds, ends an episode. 0 disables.
    tracking_error_m: float = 0.5
    tracking_error_s: float = 1.0
    # Episode length cap in control steps; 0 means none.
    max_episode_steps: int = 0

    @property
    def substeps(self) -> int:
        ratio = self.sim_hz / self.control_hz
        if self.control_hz <= 0 or ratio < 1 or abs(ratio - round(ratio)) > 1e-6:
            raise ValueError(
                f"sim_hz ({self.sim_hz}) must be a positive whole multiple of control_hz ({self.control_hz})"
            )
        return int(round(ratio))


@dataclass
class StepResult:
    """What one control step returns; arrays have N rows."""

    state: np.ndarray  # [N, D] s of the simulated characters
    ref_state: np.ndarray  # [N, D] s of the reference at the same time
    kin: KinState  # raw simulated state (the reference's: BatchedSim.reference_state())
    fell: np.ndarray  # [N] bool
    tracking_failed: np.ndarray  # [N] bool
    clip_ended: np.ndarray  # [N] bool
    timeout: np.ndarray  # [N] bool
    done: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.done = self.fell | self.tracking_failed | self.clip_ended | self.timeout


class BatchedSim:
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
        self.config = config or SimConfig()
        self.substeps = self.config.substeps
        self.model = character.model
        self.model.opt.timestep = 1.0 / self.config.sim_hz
        lib_dt = float(np.mean(library.dt))
        if abs(lib_dt * self.config.control_hz - 1.0) > 0.02:
            raise ValueError(
                f"library sampled at {1 / lib_dt:.2f} Hz, simulator controls at {self.config.control_hz} Hz"
            )
        self.num_envs = num_envs
        self.rng = np.random.default_rng(seed)
        self.datas = [mujoco.MjData(self.model) for _ in range(num_envs)]
        nb = character.num_bodies
        self._qpos = np.zeros((num_envs, self.model.nq))
        self._qvel = np.zeros((num_envs, self.model.nv))
        self._xpos = np.zeros((num_envs, nb, 3))
        self._xquat = np.zeros((num_envs, nb, 4))
        self._cvel = np.zeros((num_envs, nb, 6))
        self._com = np.zeros((num_envs, 3))
        self._fell = np.zeros(num_envs, bool)
        self.clip_id = np.zeros(num_envs, int)
        self.start_frame = np.zeros(num_envs, int)
        self.steps = np.zeros(num_envs, int)
        self._bad_head_steps = np.zeros(num_envs, int)
        allowed = [self.model.geom(n).id for n in self.config.allowed_contacts] + [character.floor_geom]
        self._fall_geom = np.ones(self.model.ngeom, bool)  # lookup: does touching this geom end the episode
        self._fall_geom[allowed] = False
        self._fall_on_contact = len(self.config.allowed_contacts) > 0
        self._head_limit_steps = int(np.ceil(self.config.tracking_error_s * self.config.control_hz))
        self.reset()

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
        self.set_state(env_ids, ref.qpos, ref.qvel)
        self.clip_id[env_ids] = clip_ids
        self.start_frame[env_ids] = frames
        self.steps[env_ids] = 0
        self._bad_head_steps[env_ids] = 0
        # The environments now hold exactly the reference state, whose s is precomputed.
        return self.library.features(clip_ids, frames)

    def set_state(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Put environments into the given generalised state (positions and contacts computed)."""
        ctrl = self.character.qpos_to_action(qpos)
        for row, i in enumerate(env_ids):
            d = self.datas[i]
            # Everything a step reads from the past: time, state, controls and the solver's
            # warm start (zeroed so that a reset environment's future depends on its state only).
            d.time = 0.0
            d.qpos[:] = qpos[row]
            d.qvel[:] = qvel[row]
            d.ctrl[:] = ctrl[row]
            d.qacc_warmstart[:] = 0.0
            mujoco.mj_forward(self.model, d)
            self._gather(i, d)

    # Step ------------------------------------------------------------------
    def step(self, actions: np.ndarray) -> StepResult:
        """Apply PD targets [N, 28] for one control step."""
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must be [{self.num_envs}, {self.action_dim}], got {list(actions.shape)}")
        m, k = self.model, self.substeps
        for i, d in enumerate(self.datas):
            d.ctrl[:] = actions[i]
            mujoco.mj_step2(m, d)
            if k > 1:
                mujoco.mj_step(m, d, nstep=k - 1)
            mujoco.mj_step1(m, d)
            self._gather(i, d)
        self.steps += 1
        kin = self.kin_state()
        frames = self.start_frame + self.steps
        head = self.character.head_body
        ref_head = self.library.body_positions(self.clip_id, frames, head)
        head_err = np.linalg.norm(kin.xpos[:, head] - ref_head, axis=-1)
        if self.config.tracking_error_m > 0:
            bad = head_err > self.config.tracking_error_m
            self._bad_head_steps = np.where(bad, self._bad_head_steps + 1, 0)
            tracking_failed = self._bad_head_steps >= self._head_limit_steps
        else:
            tracking_failed = np.zeros(self.num_envs, bool)
        clip_ended = self.library.is_last_frame(self.clip_id, frames)
        cap = self.config.max_episode_steps
        timeout = self.steps >= cap if cap > 0 else np.zeros(self.num_envs, bool)
        fell = self._fell.copy() if self._fall_on_contact else np.zeros(self.num_envs, bool)
        return StepResult(
            state=state_features(kin),
            ref_state=self.library.features(self.clip_id, frames),
            kin=kin,
            fell=fell,
            tracking_failed=tracking_failed,
            clip_ended=clip_ended,
            timeout=timeout,
        )

    # State access ----------------------------------------------------------
    def kin_state(self) -> KinState:
        """The simulated state of all environments (copies)."""
        w = self._cvel[..., :3]
        lin = self._cvel[..., 3:] + np.cross(w, self._xpos - self._com[:, None, :])
        return KinState(self._qpos.copy(), self._qvel.copy(), self._xpos.copy(), self._xquat.copy(), lin, w.copy())

    def reference_state(self) -> KinState:
        """The reference state at each environment's current time."""
        return self.library.state(self.clip_id, self.start_frame + self.steps)

    def _gather(self, i: int, d: mujoco.MjData) -> None:
        self._qpos[i] = d.qpos
        self._qvel[i] = d.qvel
        self._xpos[i] = d.xpos[1:]
        self._xquat[i] = d.xquat[1:]
        self._cvel[i] = d.cvel[1:]
        self._com[i] = d.subtree_com[1]
        # The character touches only the floor (or itself with self_collision), so a
        # contact involving any geom but the floor and the allowed ones is a fall.
        self._fell[i] = d.ncon > 0 and bool(self._fall_geom[d.contact.geom].any())
