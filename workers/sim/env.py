"""The batched simulator on MuJoCo C: N environments of the humanoid stepped together.

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

What does not depend on the physics (resets to reference states, the reference
bookkeeping, tracking failure, clip ends, time limits, the step's result, saving and
restoring) is `workers.sim.base.Simulator`'s, shared with the MuJoCo Warp backend
(`workers.sim.warp_sim.WarpSim`); `make_sim` builds the backend a `SimConfig` names.
`SimConfig`, `StepResult` and `without_tracking_termination` live there too and are
importable from here.

Reset is reference state initialisation from the motion library; on rough
terrain each reset character is raised just clear of the bumps under it
(`terrain.reset_lift`). Termination:
`fell` (a body other than the allowed ones, the feet by default, touches the
ground; reported but no end with `end_on_fall=False`), `tracking_failed` (head
further than `tracking_error_m` from the reference's for `tracking_error_s`), `clip_ended` (a one-shot clip ran out) and
`timeout` (`max_episode_steps`). The caller resets finished environments.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import batch as mj_batch

from workers.body.character import Character
from workers.motion.library import MotionLibrary
from workers.sim.base import BACKENDS, PhysicsArrays, SimConfig, Simulator, StepResult, without_tracking_termination

__all__ = ["BACKENDS", "BatchedSim", "SimConfig", "Simulator", "StepResult", "make_sim", "without_tracking_termination"]

# Slack (metres) of the floor-distance test that rules out fall contacts; only
# environments closer than this (plus the geoms' margins) get their contacts read.
FLOOR_SLACK_M = 0.01


def make_sim(
    character: Character,
    library: MotionLibrary,
    num_envs: int,
    config: SimConfig | None = None,
    seed: int = 0,
) -> Simulator:
    """The simulator `config.backend` names (default `SimConfig()`): `BatchedSim` (MuJoCo C) or
    `workers.sim.warp_sim.WarpSim` (MuJoCo Warp, imported only then)."""
    config = config or SimConfig()
    if config.backend == "warp":
        from workers.sim.warp_sim import WarpSim

        return WarpSim(character, library, num_envs, config, seed=seed)
    return BatchedSim(character, library, num_envs, config, seed=seed)


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


class BatchedSim(Simulator):
    """N environments in MuJoCo C (`mujoco.batch`); the interface is `Simulator`'s (float64 throughout)."""

    backend = "mujoco"

    def _build_physics(self) -> None:
        num_envs = self.num_envs
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
        # keep working. A whole MjData: get_data(i).
        self.datas = [EnvState(self, i) for i in range(num_envs)]
        self._floor_test = self._make_floor_test() if self._fall_on_contact else None
        if self._floor_test is not None:
            self._geom_xpos, self._geom_xmat = b.bind("geom_xpos"), b.bind("geom_xmat")

    def _set_physics_state(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray) -> None:
        # Everything a step reads from the past: time, state, controls and the solver's warm
        # start (zeroed so that a reset environment's future depends on its state only).
        self._time[env_ids] = 0.0
        self._qpos[env_ids] = qpos
        self._qvel[env_ids] = qvel
        self._ctrl[env_ids] = ctrl
        self._warmstart[env_ids] = 0.0
        # mj_forward, as MjData users would call it; the next step continues from its stages.
        self._batch.forward(np.unique(env_ids), stage=mujoco.mjtStage.mjSTAGE_ACC)

    def _advance(self, actions: np.ndarray) -> None:
        self._ctrl[:] = actions
        self._batch.step(nstep=self.substeps, stage=mujoco.mjtStage.mjSTAGE_VEL)

    def _arrays(self) -> PhysicsArrays:
        return PhysicsArrays(self._qpos, self._qvel, self._xpos, self._xquat, self._cvel, self._subtree_com)

    @property
    def qacc_warmstart(self) -> np.ndarray:
        """[N, nv] the solver's warm start of each environment, a live view: writes set it."""
        return self._warmstart

    def _set_warmstart(self, values: np.ndarray) -> None:
        self._warmstart[:] = values

    def warning_counts(self, warning: mujoco.mjtWarning = mujoco.mjtWarning.mjWARN_BADQACC) -> np.ndarray:
        """[N] how often each environment raised this MuJoCo warning since the simulator was made or MuJoCo last
        reset it for instability.

        mjWARN_BADQACC, _BADQPOS and _BADQVEL are the instability warnings: non-finite or huge accelerations,
        positions or velocities, after which MuJoCo resets the environment to the model's default pose with
        `mj_resetData`, which clears its warning counters before counting the one that fired: each of the
        three is therefore 1 after such a reset, however many came before (docs/warp.md, "Unstable worlds").
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
