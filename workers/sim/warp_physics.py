"""The humanoid's physics in MuJoCo Warp: nworld copies stepped together on a Warp device.

The physics of the `warp` simulator backend (docs/warp.md). `WarpPhysics` holds
nworld copies of one MjModel in MuJoCo Warp (`mujoco_warp.put_model`, one
`mujoco_warp.Data` made with `make_data(nworld=...)`) on a Warp device: "cpu" or
"cuda" / "cuda:N". It sets the state (qpos, qvel) of chosen worlds, sets controls and
the solver's warm start, advances every world by K physics steps and exposes qpos, qvel,
qacc, the warm start, body positions (xpos), body quaternions (xquat, w x y z as in
MuJoCo), body velocities (cvel) and subtree centres of mass as torch tensors, and the
contacts of every world (`contacts`). It is physics only: references, resets to
reference states, falls, clip switches and terminations are `workers.sim.warp_sim.WarpSim`'s
(`Simulator`'s interface, the same as `workers.sim.env.BatchedSim` on MuJoCo C).

A physics step is `mujoco_warp.step`, MuJoCo's `mj_step`: forward dynamics at the
current state, then the model's integrator (implicitfast for our humanoid). A control
step of K substeps is split as BatchedSim splits it in C: `step2` (finish the step
whose position and velocity stages are computed), K - 1 `step`s, then `step1` at the
new state, so that body positions read afterwards are the new state's. MuJoCo Warp
computes in float32, MuJoCo C in float64; tests/unit/test_warp_physics.py compares
the two from the same states under the same controls (the numbers: docs/warp.md).

Sizes. MuJoCo Warp allocates contacts and constraint rows up front, for all worlds:
`nconmax` contacts per world (pooled: `naconmax = nconmax * nworld` for all worlds
together) and `njmax` constraint rows per world. What does not fit is dropped and
flagged in `Data.overflow` (`overflowed()`), so the sizes must cover the worst case.
The defaults come from the model (`contact_capacity`): every geom pair that can
collide (by contype/conaffinity, on different bodies) with the most contacts its
collider makes (1 with a sphere, 2 for a capsule on a plane, 4 for a box or
cylinder on a plane, 8 otherwise); for our humanoid, whose only contacts are with the
floor, that is 29. The rows are 2 (condim - 1) per contact (pyramidal cones, the
model's) or condim (elliptic), one per limited joint and per dof with friction loss,
and 6 per equality: 128 for our humanoid. Larger values only cost memory and a little
time; MuJoCo Warp's own defaults are guesses from nv that do not look at the geoms.

Torch. The tensors `qpos`, `qvel`, `qacc`, `qacc_warmstart`, `xpos`, `xquat`, `cvel`,
`subtree_com` and `ctrl` are `warp.to_torch` views of MuJoCo Warp's arrays: no copy, on
the same device, float32, updated in place by every step (clone one to keep it). The
setters copy: NumPy or torch input is converted to float32 on the device (one
host-to-device copy from NumPy on a GPU). `overflowed()` copies nworld integers to the
host, `contacts()` the current contacts' worlds and geoms. On a GPU, `step` and `set_state`
synchronise the device before they return, so torch reads after them see the new state
whatever stream torch uses, and wait for torch's stream before they launch, so Warp's
kernels see torch's writes.

mujoco_warp and warp are imported when a `WarpPhysics` is made, not with this module,
so that everything else in workers/ runs without them; where they are missing the
error names the extra to install (`pip install -e '.[warp]'`).
"""

from __future__ import annotations

import copy
import importlib.util
from collections.abc import Callable, Sequence

import mujoco
import numpy as np
import torch

INSTALL_HINT = "pip install -e '.[warp]'"

# Contacts a collider makes between a plane and a geom of each type (MuJoCo's and MuJoCo Warp's
# primitive colliders); any other pair of primitives: at most 8 (box-box).
_PLANE_CONTACTS = {
    mujoco.mjtGeom.mjGEOM_SPHERE: 1,
    mujoco.mjtGeom.mjGEOM_ELLIPSOID: 1,
    mujoco.mjtGeom.mjGEOM_CAPSULE: 2,
    mujoco.mjtGeom.mjGEOM_CYLINDER: 4,
    mujoco.mjtGeom.mjGEOM_BOX: 4,
}
_PAIR_CONTACTS = 8
# Contact.type bit of a contact for the constraint solver (mujoco_warp's ContactType.CONSTRAINT, not exported);
# the others are collision-sensor contacts, which MuJoCo C does not list in MjData.contact.
_CONSTRAINT_CONTACT = 1
_PRIMITIVES = set(_PLANE_CONTACTS) | {mujoco.mjtGeom.mjGEOM_PLANE}


class WarpUnavailable(ImportError):
    """mujoco_warp or warp is not installed: the `warp` extra is missing."""


def warp_available() -> bool:
    """Whether mujoco_warp and warp can be imported (looked up, not imported)."""
    try:
        return all(importlib.util.find_spec(name) is not None for name in ("mujoco_warp", "warp"))
    except ValueError:  # a module set to None in sys.modules (blocked): not importable
        return False


def _import_warp():
    try:
        import mujoco_warp as mjw
        import warp as wp
    except ImportError as e:
        raise WarpUnavailable(
            f"the MuJoCo Warp backend needs the packages mujoco-warp and warp-lang ({e}); install them with "
            f"{INSTALL_HINT}"
        ) from e
    return mjw, wp


def contact_capacity(model: mujoco.MjModel) -> tuple[int, int]:
    """(nconmax, njmax): the most contacts and constraint rows one world of `model` can have.

    Contacts: for every geom pair that can collide (contype/conaffinity, different bodies; explicit
    pairs too), the most its collider makes. Rows: 2 (condim - 1) per contact with pyramidal cones,
    condim with elliptic ones (the largest condim of the model), one per limited joint and per dof
    with friction loss, 6 per equality. Meshes, height fields and SDFs are refused: their colliders
    make more contacts than a table can say; pass nconmax and njmax yourself for those."""
    kinds = model.geom_type
    unsupported = sorted({mujoco.mjtGeom(int(k)).name for k in kinds if int(k) not in _PRIMITIVES})
    if unsupported:
        raise ValueError(f"no contact bound for geom types {unsupported}: pass nconmax and njmax to WarpPhysics")

    def most(a: int, b: int) -> int:
        ka, kb = int(kinds[a]), int(kinds[b])
        if mujoco.mjtGeom.mjGEOM_SPHERE in (ka, kb):
            return 1
        if ka == mujoco.mjtGeom.mjGEOM_PLANE:
            return _PLANE_CONTACTS.get(kb, 0)  # plane-plane: no collider
        if kb == mujoco.mjtGeom.mjGEOM_PLANE:
            return _PLANE_CONTACTS.get(ka, 0)
        return _PAIR_CONTACTS

    ct, ca, body = model.geom_contype, model.geom_conaffinity, model.geom_bodyid
    ncon = 0
    for a in range(model.ngeom):
        for b in range(a + 1, model.ngeom):
            if body[a] != body[b] and ((ct[a] & ca[b]) or (ct[b] & ca[a])):
                ncon += most(a, b)
    ncon += sum(most(int(model.pair_geom1[p]), int(model.pair_geom2[p])) for p in range(model.npair))
    condim = int(max(model.geom_condim.max(initial=1), model.pair_dim.max(initial=1)))
    elliptic = model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    rows_per_contact = condim if elliptic or condim == 1 else 2 * (condim - 1)
    nlimit = int(model.jnt_limited.sum())
    nfriction = int((model.dof_frictionloss > 0).sum())
    return max(ncon, 1), max(ncon * rows_per_contact + nlimit + nfriction + 6 * model.neq, 1)


class WarpPhysics:
    """nworld copies of `model` in MuJoCo Warp on `device`; state and bodies as torch tensors.

    Args:
      model: the compiled model (e.g. `Character.model`); copied to the device, later edits do
        not reach it. Its timestep is the physics step.
      nworld: number of worlds.
      device: the Warp device, "cpu" or "cuda" / "cuda:N".
      nconmax, njmax: contacts and constraint rows per world; default `contact_capacity(model)`.
      graphs: replay each step(K) and the forward pass from a Warp graph captured at its first call (a CUDA
        graph on a GPU, a recorded launch list on the CPU): one launch instead of a Python call per kernel.

    All worlds start at the model's qpos0 with zero velocity and controls, positions computed.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        nworld: int,
        device: str = "cpu",
        nconmax: int | None = None,
        njmax: int | None = None,
        graphs: bool = True,
    ):
        if nworld < 1:
            raise ValueError(f"nworld must be at least 1, got {nworld}")
        mjw, wp = _import_warp()
        self._mjw, self._wp = mjw, wp
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no line per kernel module loaded
        wp.init()
        self.device = wp.get_device(device)
        default_con, default_j = contact_capacity(model) if nconmax is None or njmax is None else (0, 0)
        self.nconmax = int(nconmax if nconmax is not None else default_con)
        self.njmax = int(njmax if njmax is not None else default_j)
        self.nworld = int(nworld)
        self.graphs = graphs
        self._graphs: dict[object, object] = {}  # nstep (or "forward") -> its captured graph
        self.nq, self.nv, self.nu, self.nbody = model.nq, model.nv, model.nu, model.nbody
        self._model = copy.deepcopy(model)  # for get_data
        with wp.ScopedDevice(self.device):
            self.m = mjw.put_model(model)
            self.d = mjw.make_data(model, nworld=self.nworld, nconmax=self.nconmax, njmax=self.njmax)
            mjw.forward(self.m, self.d)  # positions of qpos0, as MjData users see after mj_forward
        self.torch_device = torch.device("cuda", self.device.ordinal) if self.device.is_cuda else torch.device("cpu")
        # Zero-copy views; MuJoCo Warp writes these arrays in place, so the views stay live.
        self._qpos = wp.to_torch(self.d.qpos)
        self._qvel = wp.to_torch(self.d.qvel)
        self._ctrl = wp.to_torch(self.d.ctrl)
        self._time = wp.to_torch(self.d.time)
        self._warmstart = wp.to_torch(self.d.qacc_warmstart)
        self._xpos = wp.to_torch(self.d.xpos)
        self._xquat = wp.to_torch(self.d.xquat)
        self._qacc = wp.to_torch(self.d.qacc)
        self._cvel = wp.to_torch(self.d.cvel)
        self._subtree_com = wp.to_torch(self.d.subtree_com)
        # Contacts of all worlds in one pool: the first nacon rows (at most naconmax) are this state's.
        self._nacon = wp.to_torch(self.d.nacon)
        self._contact_world = wp.to_torch(self.d.contact.worldid)
        self._contact_geom = wp.to_torch(self.d.contact.geom)
        self._contact_type = wp.to_torch(self.d.contact.type)
        # MuJoCo C's instability check and reset (`workers.sim.warp_kernels`), with its counters per world.
        from workers.sim import warp_kernels

        self._kernels = warp_kernels
        self._qpos0 = wp.array(np.asarray(model.qpos0, np.float32), dtype=float, device=self.device)
        self._unstable = wp.zeros((self.nworld, 3), dtype=int, device=self.device)
        self._sync()

    # State -----------------------------------------------------------------
    @property
    def qpos(self) -> torch.Tensor:
        """[nworld, nq] generalised positions (a live view)."""
        return self._qpos

    @property
    def qvel(self) -> torch.Tensor:
        """[nworld, nv] generalised velocities (a live view)."""
        return self._qvel

    @property
    def ctrl(self) -> torch.Tensor:
        """[nworld, nu] controls (a live view; writes set them)."""
        return self._ctrl

    @property
    def xpos(self) -> torch.Tensor:
        """[nworld, nbody, 3] body positions, the world body included (a live view)."""
        return self._xpos

    @property
    def xquat(self) -> torch.Tensor:
        """[nworld, nbody, 4] body orientations, w x y z (a live view)."""
        return self._xquat

    @property
    def qacc(self) -> torch.Tensor:
        """[nworld, nv] generalised accelerations of the last step or forward (a live view)."""
        return self._qacc

    @property
    def qacc_warmstart(self) -> torch.Tensor:
        """[nworld, nv] the solver's warm start, the next step's first guess of qacc (a live view; writes set it)."""
        return self._warmstart

    @property
    def cvel(self) -> torch.Tensor:
        """[nworld, nbody, 6] body velocities, com-based, rotation then translation, as MuJoCo's cvel (a live view)."""
        return self._cvel

    @property
    def subtree_com(self) -> torch.Tensor:
        """[nworld, nbody, 3] centre of mass of each body's subtree (a live view)."""
        return self._subtree_com

    def contacts(self) -> tuple[np.ndarray, np.ndarray]:
        """(world [n], geom [n, 2]): the contacts of the current state, every world's, as NumPy copies.

        The constraint contacts of MuJoCo Warp's contact pool (those MuJoCo C lists in MjData.contact),
        in MuJoCo Warp's order (by collision pair, not by world). What did not fit in the pool is
        missing: see `overflowed()`. On a GPU this copies the n rows to the host."""
        n = min(int(self._nacon[0]), self.d.naconmax)
        keep = (self._contact_type[:n] & _CONSTRAINT_CONTACT) != 0
        world, geom = self._contact_world[:n][keep], self._contact_geom[:n][keep]
        return world.cpu().numpy().astype(np.int64), geom.cpu().numpy().astype(np.int64)

    def body_states(self) -> torch.Tensor:
        """[nworld, nbody - 1, 13] float32 body states on the device (a new tensor) of every body but the world:
        position, rotation (w x y z), and linear and angular velocity at the body's origin (cvel's linear part,
        given at the root's subtree centre of mass, moved there: v + w x r), `workers.models.body_state`'s layout."""
        xpos, cvel = self._xpos[:, 1:], self._cvel[:, 1:]
        w = cvel[..., :3]
        lin = cvel[..., 3:] + torch.linalg.cross(w, xpos - self._subtree_com[:, 1:2], dim=-1)
        return torch.cat((xpos, self._xquat[:, 1:], lin, w), dim=-1)

    def worlds_touching(self, geoms: torch.Tensor) -> torch.Tensor:
        """[nworld] bool on the device: whether a contact of the current state (as `contacts` lists them) involves
        a geom that the mask `geoms` [ngeom] (bool, on the device) marks. Computed over the whole pool there, with
        no copy and no wait for the contact count."""
        rows = torch.arange(self._contact_world.shape[0], device=self.torch_device)
        live = (rows < self._nacon[0].clamp(max=self.d.naconmax)) & ((self._contact_type & _CONSTRAINT_CONTACT) != 0)
        geom = self._contact_geom.long()
        hit = live & ((geom >= 0) & geoms[geom.clamp(min=0)]).any(dim=1)  # geom -1: a flex (none in our models)
        touched = torch.zeros(self.nworld, dtype=torch.int32, device=self.torch_device)
        touched.index_add_(0, self._contact_world.long().clamp(0, self.nworld - 1), hit.to(torch.int32))
        return touched > 0

    @property
    def time(self) -> torch.Tensor:
        """[nworld] simulated time of each world since its state was last set (a live view)."""
        return self._time

    def set_state(
        self, world_ids: Sequence[int] | np.ndarray | torch.Tensor, qpos: object, qvel: object | None = None
    ) -> None:
        """Put worlds `world_ids` into the state (qpos [n, nq], qvel [n, nv]; zero without qvel).

        As BatchedSim.set_state: their time and the solver's warm start are zeroed, so that their
        future depends on the state and controls only; then the forward dynamics of every world are
        recomputed (body positions of the new states; the other worlds' state is untouched)."""
        ids = self._ids(world_ids)
        if len(ids) == 0:
            return
        self._qpos[ids] = self._tensor(qpos, (len(ids), self.nq))
        self._qvel[ids] = 0.0 if qvel is None else self._tensor(qvel, (len(ids), self.nv))
        self._time[ids] = 0.0
        self._warmstart[ids] = 0.0
        self._run("forward", self._forward)
        self._sync()

    def set_ctrl(self, ctrl: object, world_ids: Sequence[int] | np.ndarray | torch.Tensor | None = None) -> None:
        """Set the controls [n, nu] of worlds `world_ids` (all worlds by default); they hold until set again."""
        if world_ids is None:
            self._ctrl[:] = self._tensor(ctrl, (self.nworld, self.nu))
        else:
            ids = self._ids(world_ids)
            self._ctrl[ids] = self._tensor(ctrl, (len(ids), self.nu))

    def set_qacc_warmstart(self, values: object) -> None:
        """Set the solver's warm start [nworld, nv] of every world (as saved from `qacc_warmstart`)."""
        self._warmstart[:] = self._tensor(values, (self.nworld, self.nv))

    def step(self, nstep: int = 1) -> None:
        """Advance every world by `nstep` physics steps under the current controls (held for all of them).

        As BatchedSim does it in C: the data always holds the position and velocity stages of the
        current state (`mujoco_warp.step1`, MuJoCo's mj_step1), so a call finishes that step with
        `step2` (actuation, constraint solve, integration), takes `nstep - 1` whole `mujoco_warp.step`s
        and ends with `step1` at the new state: exactly `nstep` mj_steps, and the body positions read
        afterwards are those of the new state."""
        if nstep < 0:
            raise ValueError(f"nstep must be non-negative, got {nstep}")
        if nstep == 0:
            return
        self._run(nstep, self._substeps)
        self._sync()

    def _substeps(self, nstep: int) -> None:
        mjw = self._mjw
        mjw.step2(self.m, self.d)
        self._reset_unstable(check_acc=True)
        for _ in range(nstep - 1):
            mjw.step(self.m, self.d)
            self._reset_unstable(check_acc=True)
        mjw.step1(self.m, self.d)

    def _forward(self, _: object) -> None:
        self._reset_unstable(check_acc=False)  # mj_forward checks the positions and velocities first
        self._mjw.forward(self.m, self.d)

    def _reset_unstable(self, check_acc: bool) -> None:
        """MuJoCo C's checks after a physics step's integration (`warp_kernels.reset_unstable`): the step's qacc
        (mj_checkAcc, which MuJoCo C runs before integrating) and the new qpos and qvel (mj_checkPos and
        mj_checkVel, which it runs at the start of the next step or forward)."""
        d = self.d
        arrays = (d.qpos, d.qvel, d.qacc, d.ctrl, d.act, d.qacc_warmstart, d.time, self._unstable)
        self._wp.launch(self._kernels.reset_unstable, dim=self.nworld, inputs=[int(check_acc), self._qpos0, *arrays])

    def unstable_counts(self) -> dict[str, np.ndarray]:
        """{"qacc" | "qpos" | "qvel": [nworld] int}: 1 for the check that failed at a world's last reset for
        instability, 0 for the others (MuJoCo C's warning counters, which that reset clears first); all 0 for a
        world never reset that way. Copied to the host."""
        counts = self._unstable.numpy()
        return {name: counts[:, i].copy() for i, name in enumerate(self._kernels.FIELDS)}

    def _run(self, key: object, launches: Callable[[object], None]) -> None:
        """`launches(key)` on the device: replayed from the graph captured at its first call when `graphs` is
        on (one launch from C instead of one Python call per kernel), called directly otherwise."""
        wp = self._wp
        if self.device.is_cuda:  # torch's writes to the arrays (its own stream) land before Warp's kernels read them
            torch.cuda.current_stream(self.torch_device).synchronize()
        if not self.graphs:
            with wp.ScopedDevice(self.device):
                launches(key)
            return
        graph = self._graphs.get(key)
        if graph is None:
            # The first call runs directly, so that Warp loads the modules these kernels are in (a capture cannot
            # load one) and no others: forcing every imported module to load (`force_module_load`) compiled all of
            # mujoco_warp's, its flex, SDF and render kernels too, in every process, minutes on a cold cache. Then
            # the same launches are captured, not run, for the calls after.
            with wp.ScopedDevice(self.device):
                launches(key)
            with wp.ScopedDevice(self.device), wp.ScopedCapture(force_module_load=False) as capture:
                launches(key)
            self._graphs[key] = capture.graph
            return
        wp.capture_launch(graph)

    def forward(self) -> None:
        """Recompute positions, velocities and accelerations at the current state (mj_forward), for all worlds."""
        self._run("forward", self._forward)
        self._sync()

    def overflowed(self) -> np.ndarray:
        """[nworld] bool: contacts or constraint rows that did not fit (nconmax/njmax too small) since the
        data was made; such a world's physics dropped them and is not MuJoCo's any more."""
        mjw = self._mjw
        capacity = mjw.OverflowType
        mask = int(capacity.NEFC | capacity.BROADPHASE | capacity.NARROWPHASE | capacity.NJMAX_NNZ)
        return (self.d.overflow.numpy() & mask) != 0

    def get_data(self, world: int) -> mujoco.MjData:
        """A MuJoCo C MjData with world `world`'s state and computed quantities (a copy, for rendering or
        any mj_ function; float32 values widened)."""
        out = mujoco.MjData(self._model)
        self._mjw.get_data_into(out, self._model, self.d, world_id=int(world))
        return out

    # Helpers ---------------------------------------------------------------
    def _ids(self, world_ids: Sequence[int] | np.ndarray | torch.Tensor) -> torch.Tensor:
        if isinstance(world_ids, torch.Tensor):
            ids = world_ids.detach().to("cpu", torch.int64).reshape(-1)
        else:
            ids = torch.as_tensor(np.asarray(world_ids, dtype=np.int64).reshape(-1))
        if len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= self.nworld):
            raise IndexError(f"world ids must be in [0, {self.nworld}), got {ids.tolist()}")
        return ids.to(self.torch_device)

    def _tensor(self, values: object, shape: tuple[int, int]) -> torch.Tensor:
        t = torch.as_tensor(values).to(device=self.torch_device, dtype=torch.float32)
        if tuple(t.shape) != shape:
            raise ValueError(f"expected shape {list(shape)}, got {list(t.shape)}")
        return t

    def _sync(self) -> None:
        if self.device.is_cuda:
            self._wp.synchronize_device(self.device)
