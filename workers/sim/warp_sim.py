"""The batched simulator on MuJoCo Warp: `workers.sim.base.Simulator`'s interface over `WarpPhysics`.

`WarpSim` is what `workers.sim.env.make_sim` builds for `SimConfig(backend="warp")`: the same
constructor, methods and results as `BatchedSim` (MuJoCo C), with the N environments as
the worlds of one `WarpPhysics` on `SimConfig.device` ("cpu", "cuda" or "cuda:N"). What does
not depend on the physics (resets to reference states, reference bookkeeping, tracking
failure, clip ends and switches, time limits, the step's result, save and restore) is the
shared `Simulator`'s, so it is the same code on both backends.

A control step sets the controls of every world and advances them by K physics steps, split
as BatchedSim splits it (`WarpPhysics.step`). The controls come as NumPy or, from a policy acting
on the device, as a tensor taken there as it is. What leaves the device after a step is what the
step reports, computed on the device first: the head's positions (N x 3, for the tracking-failure
test) and the fall flags. The body states [N, B, 13] (each body's linear velocity moved from the
subtree's centre of mass to its origin, and packed) are made there in float32; the recorders and
policies beside this simulator read them, and the whole state, there (`StepResult.on_device`). Host
copies are made only when read: the body states (`StepResult.body_states`), the `KinState` (qpos and
qvel copied, everything widened to float64, as BatchedSim's arrays are float64) and the state
features s (computed on the device). MuJoCo Warp computes in float32, so all of them hold float32
values (tests/unit/test_warp_sim.py and docs/warp.md compare the two backends). A reset environment
holds the float32 rounding of the reference state; the state features `reset` returns are the
library's precomputed ones, as on MuJoCo C.

Falls follow BatchedSim's rule: a contact of the new state that involves any geom but the floor
and the allowed ones (`SimConfig.allowed_contacts`). They are found on the device over MuJoCo
Warp's contact pool (`WarpPhysics.worlds_touching`: the rows of the current state, whose world and
geom pair are read there), which is small (29 contacts per world at most for our humanoid), so no
floor-distance pre-test is needed; N flags are copied to the host.

What MuJoCo C does that MuJoCo Warp does not, and what this class does instead:
- Unstable worlds. MuJoCo C resets an environment to the model's default pose, mid-step, when its
  positions, velocities or accelerations are non-finite or huge (> mjMAXVAL), and counts a warning
  (mjWARN_BADQPOS, _BADQVEL, _BADQACC). MuJoCo Warp carries on with NaNs (or, for a NaN in a
  quaternion, with a normalised one and different physics). `WarpPhysics` runs MuJoCo C's checks and
  reset in a kernel of its own after every physics step and before every forward pass
  (`workers.sim.warp_kernels`), on the device and inside the step's graph, and `warning_counts` reads
  its counters. The one difference: MuJoCo C checks the accelerations before it integrates and
  integrates the reset world within the same physics step, where the kernel checks them after the
  integration, so a world reset for its accelerations is one physics step (1/480 s) behind MuJoCo C's.
- Rough terrain is refused (`terrain.kind` must be "flat"): MuJoCo Warp's height-field collider keeps
  at most 4 contacts per geom pair where MuJoCo C keeps up to 50, and `contact_capacity` has no bound
  for height fields, so the physics would not be MuJoCo C's.
- `datas` (BatchedSim's per-environment views, which nothing in the project reads any more) is not
  provided; `get_data(i)` copies a world into a MuJoCo C MjData.
"""

from __future__ import annotations

import functools
from typing import Any

import mujoco
import numpy as np
import torch

from workers.models import body_state
from workers.models.device_features import DeviceReference, DeviceState
from workers.sim.base import PhysicsArrays, Simulator
from workers.sim.warp_physics import WarpPhysics
from workers.types import KinState

_UNSTABLE = {  # MuJoCo C's warning for a non-finite or huge value of each field (`WarpPhysics.unstable_counts`)
    mujoco.mjtWarning.mjWARN_BADQACC: "qacc",
    mujoco.mjtWarning.mjWARN_BADQPOS: "qpos",
    mujoco.mjtWarning.mjWARN_BADQVEL: "qvel",
}
_FULL = (mujoco.mjtWarning.mjWARN_CONTACTFULL, mujoco.mjtWarning.mjWARN_CNSTRFULL)


class WarpSim(Simulator):
    """N environments in MuJoCo Warp on `config.device`; the interface is `Simulator`'s (see the module)."""

    backend = "warp"
    computes_on_device = True

    def _check_config(self) -> None:
        super()._check_config()
        kind = self.config.terrain.kind
        if kind != "flat":
            raise NotImplementedError(
                f"terrain.kind={kind!r} does not run on sim backend 'warp': MuJoCo Warp's height-field collider "
                "keeps at most 4 contacts per geom pair (MuJoCo C up to 50) and contact_capacity has no bound for "
                "height fields; use terrain.kind='flat' or sim backend 'mujoco' (docs/warp.md)"
            )

    def _build_physics(self) -> None:
        self.physics = WarpPhysics(self.model, self.num_envs, device=self.config.device)
        self._reference: DeviceReference | None = None  # the library on the device, made when first asked for
        self._fall_mask: torch.Tensor | None = None  # `_fall_geom` on the device

    def _set_physics_state(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray) -> None:
        self.physics.set_ctrl(ctrl, env_ids)
        self.physics.set_state(env_ids, qpos, qvel)  # zero time and warm start, forward dynamics

    def _advance(self, actions: np.ndarray | torch.Tensor) -> None:
        self.physics.set_ctrl(actions)
        self.physics.step(self.substeps)  # unstable worlds reset within it (`WarpPhysics`)

    def _arrays(self) -> PhysicsArrays:
        p = self.physics
        views = (p.qpos, p.qvel, p.xpos, p.xquat, p.cvel, p.subtree_com)
        # One device-to-host copy of all six (on a GPU, one transfer and one synchronisation per step).
        flat = torch.cat([v.reshape(self.num_envs, -1) for v in views], dim=1).cpu().numpy().astype(np.float64)
        widths = np.cumsum([v[0].numel() for v in views])[:-1]
        parts = np.split(flat, widths, axis=1)
        return PhysicsArrays(*(a.reshape(v.shape) for a, v in zip(parts, views, strict=True)))

    def _observe(self) -> dict[str, Any]:
        bs = self.physics.body_states()
        p = self.physics
        on_device = DeviceState(p.qpos.clone(), p.qvel.clone(), bs)
        packed = functools.cache(lambda: bs.cpu().numpy())  # copied when read: a worker keeps them on the device
        head = bs[:, self.character.head_body, :3].cpu().numpy().astype(np.float64)  # N x 3: the only copy a step
        return {
            "kin_source": lambda: self._kin(on_device.qpos.cpu().numpy(), on_device.qvel.cpu().numpy(), packed()),
            "packed": packed,
            "features": lambda: body_state.features(bs).cpu().numpy(),
            "on_device": on_device,
            "head_xpos": head,
        }

    @property
    def torch_device(self) -> torch.device:
        return self.physics.torch_device

    def device_body_states(self) -> torch.Tensor:
        """[N, B, 13] float32 body states of the current state, on the device (a new tensor, not a view)."""
        return self.physics.body_states()

    def _to_host(self, bs: torch.Tensor) -> tuple[KinState, np.ndarray]:
        """The `KinState` (float64) and body states (float32) of device body states: one copy with qpos, qvel."""
        p, n = self.physics, self.num_envs
        flat = torch.cat((p.qpos, p.qvel, bs.reshape(n, -1)), dim=1).cpu().numpy()
        nq, nv = p.qpos.shape[1], p.qvel.shape[1]
        packed = flat[:, nq + nv :].reshape(bs.shape)
        return self._kin(flat[:, :nq], flat[:, nq : nq + nv], packed), packed

    @staticmethod
    def _kin(qpos: np.ndarray, qvel: np.ndarray, packed: np.ndarray) -> KinState:
        """A `KinState` (float64 copies) of float32 qpos, qvel and body states."""
        parts = (packed[..., part] for part in (body_state.POS, body_state.QUAT, body_state.LIN, body_state.ANG))
        return KinState(qpos.astype(np.float64), qvel.astype(np.float64), *(a.astype(np.float64) for a in parts))

    def kin_state(self) -> KinState:
        """The simulated state of all environments (host copies, float64 holding float32 values), made on the device."""
        return self._to_host(self.physics.body_states())[0]

    def body_states(self, env_ids: np.ndarray | None = None) -> np.ndarray:
        packed = self.physics.body_states().cpu().numpy()
        return packed if env_ids is None else packed[env_ids]

    def device_reference(self) -> DeviceReference:
        if self._reference is None:
            self._reference = DeviceReference(self.library, self.physics.torch_device)
        return self._reference

    def device_state(self) -> DeviceState:
        p = self.physics
        return DeviceState(p.qpos.clone(), p.qvel.clone(), self.physics.body_states())

    def _contact_falls(self) -> np.ndarray:
        if self._fall_mask is None:
            self._fall_mask = torch.as_tensor(self._fall_geom, device=self.physics.torch_device)
        return self.physics.worlds_touching(self._fall_mask).cpu().numpy()  # found on the device, N flags copied

    @property
    def qacc_warmstart(self) -> np.ndarray:
        """[N, nv] float32, the solver's warm start of each environment: on Warp's CPU device a live view
        (writes set it), on a GPU a copy (set it through `restore_state`)."""
        return self.physics.qacc_warmstart.detach().cpu().numpy()

    def _set_warmstart(self, values: np.ndarray) -> None:
        self.physics.set_qacc_warmstart(np.asarray(values))

    def warning_counts(self, warning: mujoco.mjtWarning = mujoco.mjtWarning.mjWARN_BADQACC) -> np.ndarray:
        """[N] each environment's count of this MuJoCo warning, as MuJoCo C's `BatchedSim.warning_counts`.

        MuJoCo Warp keeps no warning counters. mjWARN_BADQACC, _BADQPOS and _BADQVEL are `WarpPhysics`'s
        resets of unstable worlds (`WarpPhysics.unstable_counts`: as in MuJoCo C, 1 for the check that failed
        at an environment's last such reset, which clears the other two); mjWARN_CONTACTFULL and
        mjWARN_CNSTRFULL are 1 for a world whose contacts or constraint rows overflowed MuJoCo Warp's capacity
        since the simulator was made (`WarpPhysics.overflowed`), else 0; other warnings are 0."""
        if warning in _FULL:
            return self.physics.overflowed().astype(int)
        if warning in _UNSTABLE:
            return self.physics.unstable_counts()[_UNSTABLE[warning]].astype(int)
        return np.zeros(self.num_envs, int)

    def get_data(self, i: int) -> mujoco.MjData:
        """A MuJoCo C MjData with environment i's state and computed quantities (a copy; float32 values widened)."""
        return self.physics.get_data(int(i))

    def overflowed(self) -> np.ndarray:
        """[N] bool: environments whose contacts or constraint rows did not fit (`WarpPhysics.overflowed`)."""
        return self.physics.overflowed()
