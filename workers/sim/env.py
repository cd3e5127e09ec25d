"""The batched simulator on MuJoCo C: N environments of the humanoid stepped together (`BatchedSim`, `make_sim`).

A control step applies the PD targets [N, A] and advances every environment by K = sim_hz / control_hz physics
steps in one `mujoco.batch.Batch` (persistent: one MjData per environment), in C with the GIL released, on
`SimConfig.threads` threads: per environment `mj_step2` (the step whose position and velocity stages are already
computed), `mj_step` for the other substeps, then the position and velocity stages of the new state, so that its
bodies, velocities and contacts are known without a separate `mj_forward`. Bodies of every environment are read as
(N, ...) arrays, and the state features computed in bulk.

Falls are judged on the new state's contacts: one that involves a geom other than the floor and the allowed ones
(the feet by default). A vectorised test first rules out the environments where no fall geom can touch a plane
floor; only the others are decided on MuJoCo's own contact list, so the outcome is that of checking every list.
With self-collision, contact pairs or a floor that is not a plane (rough terrain's height field,
`workers.sim.terrain`) every environment with contacts is checked on its list.

What does not depend on the physics (resets to reference states, the reference bookkeeping, tracking failure,
clip ends, time limits, the step's result, saving and restoring) is `workers.sim.base.Simulator`'s, shared with
MuJoCo Warp (`workers.sim.warp_sim.WarpSim`); `SimConfig`, `StepResult` and `without_tracking_termination` live
there and are importable from here. Why the batch, what it was measured against, and the fall test's details:
docs/simulator.md.
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
