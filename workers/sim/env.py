"""The batched simulator: N environments of the humanoid stepped together.

A control step applies the PD targets [N, 28] and advances every environment by
K = sim_hz / control_hz physics steps; positions, rotations and velocities of
all bodies of all environments are then read as arrays, from which the state
features are computed in bulk.

Physics: one `mujoco.batch.Batch` (MuJoCo >= 3.17) holds the N environments,
each as its row of integration state (time, qpos, qvel, controls, the solver's
warm start, warning counters), and steps them in C with the GIL released, on
`SimConfig.threads` threads (default 1: the calling thread only). Per
environment a control step is `mj_step2` (finish the step whose position and
velocity stages are already computed, now with the new controls), `mj_step` for
the remaining substeps, then the position and velocity stages at the new state,
as `mj_step1` computes them, so that body positions, velocities and contacts of
the new state are known: exactly K physics steps, with no separate
`mj_forward`. The batch is *persistent* (one MjData per environment), which is
what lets the next step continue with `mj_step2` from those stages instead of
recomputing them (a non-persistent batch, one MjData reused for all, keeps the
physics in cache but recomputes them: 1.5% faster at 480/30 Hz, 7% slower at
120/30 Hz). The results are bit-identical to calling `mj_step2`,
`mj_step(nstep=K-1)` and `mj_step1` on one MjData per environment, which is what
this module did before: compared over random-policy runs at 480, 240 and 120 Hz
with resets, falls, MuJoCo's resets after bad accelerations, self-collision and
two threads, every state, feature and termination flag was equal.

Why the batch: the Python loop over environments cost ~5 µs per environment
and control step (three calls, six array copies, the contact list), ~1.5% of a
control step at 480/30 Hz but ~6% at 120/30 Hz; the batch copies the body
quantities of every environment into (N, ...) arrays in C after each call
(`bind`), so nothing per environment runs in Python any more. What remains per
control step (state features, reference lookups, the fall test, resets) is
NumPy over the whole batch.

Falls are judged on the contacts of the new state, as before: a contact that
involves any geom but the floor and the allowed ones. The contact list lives in
MjData's arena, which the batch cannot export as an array, and copying a whole
MjData out (`Batch.get_data`, ~5 µs) for every environment would cost more than
the loop did. So a vectorised test first rules out the environments where no fall
geom can touch the floor: for a plane floor, a sphere, capsule or box cannot
be in contact with it while its lowest point along the floor normal is above
the contact margin (other shapes: their bounding sphere), and 1 cm of slack
covers rounding. Only the remaining environments, those with a fall geom within
about a centimetre of the floor, are copied out and decided on MuJoCo's own
contact list, so the outcome is exactly that of checking every contact list
(random-policy runs: 2-8% more environments copied out than falls found).
When a fall geom could touch anything but the floor (self-collision, explicit
contact pairs, a floor that is not a plane), every environment with contacts is
checked on its contact list. That is the test on rough terrain, whose floor is a
height field (`workers.sim.terrain`); the ground there is the field and the
plane beyond it, both allowed like the floor.

Reset is reference state initialisation from the motion library; on rough
terrain each reset character is raised just clear of the bumps under it
(`terrain.reset_lift`). Termination:
`fell` (a body other than the allowed ones, the feet by default, touches the
ground; reported but no end with `end_on_fall=False`), `tracking_failed` (head
further than `tracking_error_m` from the reference's for `tracking_error_s`), `clip_ended` (a one-shot clip ran out) and
`timeout` (`max_episode_steps`). The caller resets finished environments.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import mujoco
import numpy as np
from mujoco import batch as mj_batch

from workers.body.character import Character
from workers.body.features import state_features
from workers.models.body_state import pack
from workers.motion.library import MotionLibrary
from workers.sim.terrain import TerrainConfig, ground_geoms, reset_lift, terrain_model
from workers.types import KinState

# Slack (metres) of the floor-distance test that rules out fall contacts; only
# environments closer than this (plus the geoms' margins) get their contacts read.
FLOOR_SLACK_M = 0.01
_YZX, _ZXY = [1, 2, 0], [2, 0, 1]  # component orders of a cross product
BACKENDS = ("mujoco", "warp")


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
    # Threads that step the environments (the caller's included). 1 by default: rollout workers
    # share the machine's cores, and results are bit-identical at any thread count.
    threads: int = 1
    # The ground: flat (the character file's floor) or a rough height field (`workers.sim.terrain`).
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    # Physics: "mujoco" (MuJoCo C, this module) or "warp" (MuJoCo Warp, `workers.sim.warp_physics`; needs the
    # warp extra, and BatchedSim does not run on it yet: docs/warp.md).
    backend: str = "mujoco"

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"sim backend must be one of {BACKENDS}, got {self.backend!r}")
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
    kin: KinState  # raw simulated state (the reference's: BatchedSim.reference_state())
    fell: np.ndarray  # [N] bool
    tracking_failed: np.ndarray  # [N] bool
    clip_ended: np.ndarray  # [N] bool
    timeout: np.ndarray  # [N] bool
    end_on_fall: bool = True  # whether `fell` ends the episode
    done: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.done = self.tracking_failed | self.clip_ended | self.timeout
        if self.end_on_fall:
            self.done = self.done | self.fell

    @cached_property
    def state(self) -> np.ndarray:
        """[N, D] s of the simulated characters (from `kin`, a copy: the same whenever it is read).

        Lazy because most callers observe through the policy's own features, and computing
        s for every step cost ~4% of a rollout worker's control step at 8 environments."""
        return state_features(self.kin)


class EnvState:
    """Environment i's state row under MjData's names; the arrays are views, so writes set its state."""

    def __init__(self, sim: BatchedSim, i: int):
        self._sim, self._i = sim, i

    @property
    def qpos(self) -> np.ndarray:
        return self._sim._qpos[self._i]

    @property
    def qvel(self) -> np.ndarray:
        return self._sim._qvel[self._i]

    @property
    def ctrl(self) -> np.ndarray:
        return self._sim._ctrl[self._i]

    @property
    def qacc_warmstart(self) -> np.ndarray:
        return self._sim.qacc_warmstart[self._i]


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
        if self.config.backend != "mujoco":
            raise NotImplementedError(
                f"BatchedSim runs on MuJoCo C only so far (sim backend {self.config.backend!r}: docs/warp.md)"
            )
        if self.config.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.config.threads}")
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
        # The batch copies the model: later edits of character.model do not reach it.
        b = mj_batch.Batch(self.model, num_envs, nthread=self.config.threads, persistent=True)
        self._batch = b
        # Live (N, ...) views: state fields are the rows themselves, the others are copied out
        # of every environment's MjData after each call (for the environments of that call).
        self._time, self._qpos, self._qvel = b.bind("time"), b.bind("qpos"), b.bind("qvel")
        self._ctrl, self._warmstart = b.bind("ctrl"), b.bind("qacc_warmstart")
        self._xpos, self._xquat = b.bind("xpos"), b.bind("xquat")
        self._cvel, self._subtree_com = b.bind("cvel"), b.bind("subtree_com")
        self._ncon = b.bind("ncon")
        self._scratch = mujoco.MjData(self.model)  # where an environment is copied to read its contacts
        # Was a list of MjData; callers that read or set d.qpos, d.qvel, d.ctrl or d.qacc_warmstart
        # (the rollout worker's state_dict) keep working. A whole MjData: get_data(i).
        self.datas = [EnvState(self, i) for i in range(num_envs)]
        self._fell = np.zeros(num_envs, bool)
        self.clip_id = np.zeros(num_envs, int)
        self.start_frame = np.zeros(num_envs, int)
        self.steps = np.zeros(num_envs, int)
        self._bad_head_steps = np.zeros(num_envs, int)
        allowed = [self.model.geom(n).id for n in self.config.allowed_contacts] + ground_geoms(self.model)
        self._fall_geom = np.ones(self.model.ngeom, bool)  # lookup: does touching this geom end the episode
        self._fall_geom[allowed] = False
        self._fall_on_contact = len(self.config.allowed_contacts) > 0
        self._floor_test = self._make_floor_test() if self._fall_on_contact else None
        if self._floor_test is not None:
            self._geom_xpos, self._geom_xmat = b.bind("geom_xpos"), b.bind("geom_xmat")
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
        # The environments now hold exactly the reference state, whose s is precomputed.
        return self.library.features(clip_ids, frames)

    def set_state(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Put environments into the given generalised state (positions and contacts computed)."""
        env_ids = np.asarray(env_ids, dtype=int)
        if len(env_ids) == 0:
            return
        # Everything a step reads from the past: time, state, controls and the solver's warm
        # start (zeroed so that a reset environment's future depends on its state only).
        self._time[env_ids] = 0.0
        self._qpos[env_ids] = qpos
        self._qvel[env_ids] = qvel
        self._ctrl[env_ids] = self.character.qpos_to_action(np.asarray(qpos))
        self._warmstart[env_ids] = 0.0
        # mj_forward, as MjData users would call it; the next step continues from its stages.
        self._batch.forward(np.unique(env_ids), stage=mujoco.mjtStage.mjSTAGE_ACC)

    # Step ------------------------------------------------------------------
    def step(self, actions: np.ndarray) -> StepResult:
        """Apply PD targets [N, 28] for one control step."""
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must be [{self.num_envs}, {self.action_dim}], got {list(actions.shape)}")
        self._ctrl[:] = actions
        self._batch.step(nstep=self.substeps, stage=mujoco.mjtStage.mjSTAGE_VEL)
        self.steps += 1
        kin = self.kin_state()
        frames = self.start_frame + self.steps
        if self.config.tracking_error_m > 0:
            head = self.character.head_body
            ref_head = self.library.body_positions(self.clip_id, frames, head)
            bad = np.linalg.norm(kin.xpos[:, head] - ref_head, axis=-1) > self.config.tracking_error_m
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
            kin=kin,
            fell=self._fell.copy(),
            tracking_failed=tracking_failed,
            clip_ended=clip_ended,
            timeout=timeout,
            end_on_fall=self.config.end_on_fall,
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
        """The simulated state of all environments (copies)."""
        xpos = self._xpos[:, 1:]
        cvel = self._cvel[:, 1:]
        w = cvel[..., :3]
        # cvel's linear part is at the root's subtree centre of mass; moved to each body's origin:
        # v + w x r. The cross product is written out (same products and order as np.cross,
        # so the same bits) because np.cross costs several times more NumPy calls.
        r = xpos - self._subtree_com[:, 1, None, :]
        lin = cvel[..., 3:] + (w[..., _YZX] * r[..., _ZXY] - w[..., _ZXY] * r[..., _YZX])
        return KinState(self._qpos.copy(), self._qvel.copy(), xpos.copy(), self._xquat[:, 1:].copy(), lin, w.copy())

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

    @property
    def qacc_warmstart(self) -> np.ndarray:
        """[N, nv] the solver's warm start of each environment, a live view: writes set it."""
        return self._warmstart

    def warning_counts(self, warning: mujoco.mjtWarning = mujoco.mjtWarning.mjWARN_BADQACC) -> np.ndarray:
        """[N] how often each environment raised this MuJoCo warning since the simulator was made.

        mjWARN_BADQACC is the instability warning: non-finite or huge accelerations, after
        which MuJoCo resets the environment to the model's default pose.
        """
        return self._batch.warning[:, int(warning), 1].astype(int)

    def get_data(self, i: int) -> mujoco.MjData:
        """A copy of environment i's whole MjData (for rendering or any mj_ function)."""
        return self._batch.get_data(int(i))

    # Falls -----------------------------------------------------------------
    def _make_floor_test(self) -> tuple[np.ndarray, ...] | None:
        """What `_contact_falls` needs to rule out floor contacts, or None where it cannot.

        It can when the fall geoms can collide with nothing but a static plane floor (by
        contype/conaffinity, with no explicit contact pairs). A geom's lowest point along the
        floor normal n lies sum_j |n . axis_j| * half_j + radius below its centre: half =
        (0, 0, half-length) and radius for a capsule, the half-sizes for a box, the radius for a
        sphere, and the bounding-sphere radius for any other shape. The test runs on all geoms
        (fewer NumPy calls than selecting the fall geoms); the others get a threshold of -inf.
        """
        m, floor = self.model, self.character.floor_geom
        fall = self._fall_geom
        if m.npair > 0 or m.geom_type[floor] != mujoco.mjtGeom.mjGEOM_PLANE or m.geom_bodyid[floor] != 0:
            return None
        ct, ca = m.geom_contype, m.geom_conaffinity
        collide = ((ct[fall, None] & ca[None, :]) | (ca[fall, None] & ct[None, :])) != 0
        collide &= m.geom_bodyid[fall, None] != m.geom_bodyid[None, :]  # one body's geoms never collide
        collide[:, floor] = False
        if collide.any():
            return None
        d = self._scratch
        mujoco.mj_kinematics(m, d)
        normal = d.geom_xmat[floor].reshape(3, 3)[:, 2].copy()
        # geom_xmat rows are row-major 3x3 rotations R; xmat @ project = n . R[:, j] for j = 0, 1, 2.
        project = np.zeros((9, 3))
        for i in range(3):
            project[3 * i + np.arange(3), np.arange(3)] = normal[i]
        size, kind, g = m.geom_size, m.geom_type, mujoco.mjtGeom
        half, radius = np.zeros((m.ngeom, 3)), m.geom_rbound.copy()
        sphere, capsule, box = (kind == g.mjGEOM_SPHERE), (kind == g.mjGEOM_CAPSULE), (kind == g.mjGEOM_BOX)
        radius[sphere | capsule] = size[sphere | capsule, 0]
        half[capsule, 2] = size[capsule, 1]
        half[box], radius[box] = size[box], 0.0
        half[~fall] = 0.0
        # Candidate when n . centre - extent < n . origin + margin + slack, i.e. n . centre - extent
        # below this threshold, with extent = sum_j |n . R[:, j]| * half_j (radius moved across).
        margin = np.maximum(m.geom_margin, m.geom_margin[floor]) + FLOOR_SLACK_M
        threshold = np.where(fall, normal @ d.geom_xpos[floor] + margin + radius, -np.inf)
        return normal, project, half, threshold

    def _contact_falls(self) -> np.ndarray:
        """[N] whether a contact of the current state involves a fall geom."""
        candidates = self._ncon > 0
        if self._floor_test is not None:
            normal, project, half, threshold = self._floor_test
            extent = np.einsum("ngj,gj->ng", np.abs(self._geom_xmat @ project), half)
            candidates &= (self._geom_xpos @ normal - extent < threshold).any(axis=1)
        fell = np.zeros(self.num_envs, bool)
        d = self._scratch
        for i in np.flatnonzero(candidates):
            self._batch.get_data(int(i), d)
            # The character touches only the floor (or itself with self_collision), so a
            # contact involving any geom but the floor and the allowed ones is a fall.
            fell[i] = d.ncon > 0 and bool(self._fall_geom[d.contact.geom].any())
        return fell
