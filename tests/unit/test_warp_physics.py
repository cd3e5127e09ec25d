"""workers.sim.warp_physics: MuJoCo Warp on Warp's CPU device against MuJoCo C, from the same states
under the same controls (on a GPU with MOCAP_WARP_DEVICE=cuda), and the captured graphs against direct
launches.

The first test to step compiles MuJoCo Warp's kernels (36-60 s on two cores; Warp caches them in
its kernel cache for later runs), hence `slow`. Tolerances: over the two control steps (32 physics
steps at 480 Hz) compared here, qpos and body positions were measured within 4e-7 and velocities within
2e-5 of MuJoCo C's float64 (docs/warp.md has the measurement over longer horizons); the bounds below
leave a margin of about 25 for other CPUs and compilers, and are still far below what a wrong step
count, control or timestep would give (1e-3 and more after one control step).
"""

from __future__ import annotations

import os
import re
import sys

import mujoco
import numpy as np
import pytest
import torch

pytest.importorskip("mujoco_warp")

from workers.sim.warp_physics import INSTALL_HINT, WarpPhysics, WarpUnavailable, contact_capacity  # noqa: E402

SUBSTEPS = 16  # one control step at 480/30 Hz
DEVICE = os.environ.get("MOCAP_WARP_DEVICE", "cpu")  # scripts/device-warp.sh runs these on cuda
POS_TOL = 1e-5  # qpos, xpos, xquat (metres, radians, quaternion components)
VEL_TOL = 5e-4  # qvel (m/s, rad/s)


@pytest.fixture(scope="module")
def model(character):
    return character.model


@pytest.fixture(scope="module")
def sim(model):
    return WarpPhysics(model, nworld=4, device=DEVICE)


def start_states(model, walk_run):
    """Four states: walk and run reference frames (feet on the floor), and two random perturbations of
    the model's qpos0 (0.9 m above the floor, falling, with random velocities)."""
    clips, frames = np.array([0, 1]), np.array([5, 10])
    ref = walk_run.state(clips, frames)
    qpos, qvel = [*ref.qpos], [*ref.qvel]
    rng = np.random.default_rng(0)
    for _ in range(2):
        q = model.qpos0.copy()
        mujoco.mj_integratePos(model, q, rng.normal(0.0, 0.5, model.nv), 0.3)
        qpos.append(q)
        qvel.append(rng.normal(0.0, 0.3, model.nv))
    return np.array(qpos), np.array(qvel), clips, frames


def c_data(model, qpos, qvel):
    d = mujoco.MjData(model)
    d.qpos[:], d.qvel[:] = qpos, qvel
    mujoco.mj_forward(model, d)
    return d


def test_contact_capacity_of_the_humanoid(model):
    # Floor contacts only: 5 spheres (1 each), 8 capsules (2), 2 boxes (4); 4 rows per pyramidal
    # contact of condim 3 and one per limited joint (12).
    assert contact_capacity(model) == (29, 29 * 4 + 12)


def test_missing_extra_is_named(model, monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco_warp", None)  # import mujoco_warp now raises ImportError
    with pytest.raises(WarpUnavailable, match="mujoco-warp.*" + re.escape(INSTALL_HINT)):
        WarpPhysics(model, nworld=1)


@pytest.mark.slow
def test_state_set_is_state_read(sim, model, walk_run):
    qpos, qvel, _, _ = start_states(model, walk_run)
    sim.set_state(range(4), np.repeat(model.qpos0[None], 4, 0), np.zeros((4, model.nv)))
    sim.set_state([3, 1], qpos[[0, 2]], qvel[[0, 2]])
    f32 = torch.float32
    assert torch.equal(sim.qpos[3].cpu(), torch.as_tensor(qpos[0], dtype=f32))
    assert torch.equal(sim.qvel[1].cpu(), torch.as_tensor(qvel[2], dtype=f32))
    # The others are untouched.
    for w in (0, 2):
        assert torch.equal(sim.qpos[w].cpu(), torch.as_tensor(model.qpos0, dtype=f32))
        assert torch.equal(sim.qvel[w].cpu(), torch.zeros(model.nv))
    # Body positions and orientations (w x y z) are those of the new states, as MuJoCo C computes them.
    for w, i in ((3, 0), (1, 2)):
        d = c_data(model, qpos[i], qvel[i])
        np.testing.assert_allclose(sim.xpos[w].cpu().numpy(), d.xpos, atol=POS_TOL)
        np.testing.assert_allclose(sim.xquat[w].cpu().numpy(), d.xquat, atol=POS_TOL)
    assert sim.xpos.shape == (4, model.nbody, 3) and sim.xquat.shape == (4, model.nbody, 4)
    # Zero-copy: the tensors are views of MuJoCo Warp's arrays.
    assert sim.qpos.data_ptr() == sim.d.qpos.ptr and sim.xpos.data_ptr() == sim.d.xpos.ptr
    with pytest.raises(ValueError, match="shape"):
        sim.set_state([0], qpos[:2], qvel[:2])
    with pytest.raises(IndexError):
        sim.set_state([4], qpos[:1], qvel[:1])


@pytest.mark.slow
def test_matches_mujoco_c_over_two_control_steps(sim, model, character, walk_run):
    qpos, qvel, clips, frames = start_states(model, walk_run)
    sim.set_state(range(4), qpos, qvel)
    datas = [c_data(model, qpos[w], qvel[w]) for w in range(4)]
    ncon = 0
    for t in range(2):
        # The references' PD targets for the walk and run worlds; the falling ones hold their start pose.
        ctrl = np.concatenate([walk_run.pd_targets(clips, frames + t + 1), character.qpos_to_action(qpos[2:])])
        sim.set_ctrl(ctrl)
        sim.step(SUBSTEPS)
        for w, d in enumerate(datas):
            d.ctrl[:] = ctrl[w]
            mujoco.mj_step(model, d, nstep=SUBSTEPS)
            mujoco.mj_step1(model, d)  # positions of the new state, as WarpPhysics.step leaves them
            ncon += d.ncon
        np.testing.assert_allclose(sim.time.cpu().numpy(), (t + 1) * SUBSTEPS * model.opt.timestep, rtol=1e-5)
        for w, d in enumerate(datas):
            np.testing.assert_allclose(sim.qpos[w].cpu().numpy(), d.qpos, atol=POS_TOL, err_msg=f"world {w}, step {t}")
            np.testing.assert_allclose(sim.qvel[w].cpu().numpy(), d.qvel, atol=VEL_TOL, err_msg=f"world {w}, step {t}")
            np.testing.assert_allclose(sim.xpos[w].cpu().numpy(), d.xpos, atol=POS_TOL, err_msg=f"world {w}, step {t}")
            np.testing.assert_allclose(
                sim.xquat[w].cpu().numpy(), d.xquat, atol=POS_TOL, err_msg=f"world {w}, step {t}"
            )
    assert ncon > 0  # the comparison covered contacts with the floor
    assert not sim.overflowed().any()
    # The worlds moved (a step that did nothing would not be within the tolerance of MuJoCo C either).
    assert np.abs(sim.qpos.cpu().numpy() - qpos).max() > 100 * POS_TOL


@pytest.mark.slow
def test_graph_replay_steps_as_direct_launches_do(sim, model, character, walk_run):
    """`sim` replays captured graphs (the default); a twin launches every kernel from Python. The same states,
    controls and steps (a state set between them replays the captured forward pass) give the same states: to
    the bit on the CPU, where kernels run in a fixed order; within float rounding on a GPU."""
    qpos, qvel, clips, frames = start_states(model, walk_run)
    direct = WarpPhysics(model, nworld=4, device=DEVICE, graphs=False)
    exact = direct.device.is_cpu
    for t in range(3):
        if t == 1:  # a mid-run reset of two worlds
            for p in (sim, direct):
                p.set_state([0, 2], qpos[[1, 3]], qvel[[1, 3]])
        if t == 0:
            for p in (sim, direct):
                p.set_state(range(4), qpos, qvel)
        ctrl = np.concatenate([walk_run.pd_targets(clips, frames + t + 1), character.qpos_to_action(qpos[2:])])
        for p in (sim, direct):
            p.set_ctrl(ctrl)
            p.step(SUBSTEPS)
        for name in ("qpos", "qvel", "xpos", "xquat", "cvel"):
            a, b = getattr(sim, name).cpu(), getattr(direct, name).cpu()
            if exact:
                assert torch.equal(a, b), (name, t)
            else:
                torch.testing.assert_close(a, b, rtol=0, atol=VEL_TOL if name in ("qvel", "cvel") else POS_TOL)
    assert SUBSTEPS in sim._graphs and "forward" in sim._graphs and not direct._graphs
    assert np.abs(sim.qpos.cpu().numpy() - qpos).max() > 100 * POS_TOL  # they moved


def test_a_graph_is_captured_without_loading_every_module_warp_has(model, monkeypatch):
    """`force_module_load=True` compiled every imported Warp module (mujoco_warp's flex, SDF and render kernels
    too) in every process that captured a graph: minutes on a fresh machine. The first call runs directly
    instead, loading what it launches, and the capture after it loads nothing."""
    import warp

    forced: list[bool] = []
    capture = warp.ScopedCapture

    def recording(*args, **kwargs):
        forced.append(bool(kwargs.get("force_module_load", args[2] if len(args) > 2 else None)))
        return capture(*args, **kwargs)

    monkeypatch.setattr(warp, "ScopedCapture", recording)
    physics = WarpPhysics(model, nworld=2, device=DEVICE)
    physics.step(SUBSTEPS)
    physics.step(SUBSTEPS)
    assert forced and not any(forced)
    assert SUBSTEPS in physics._graphs


@pytest.mark.slow
def test_worlds_touching_reads_only_the_current_contacts(sim, model, walk_run):
    """On the device, from the whole contact pool: the worlds with a contact involving a marked geom, as the
    current state's contacts (`contacts()`) say; rows left in the pool from an earlier state do not count."""
    floor = torch.zeros(model.ngeom, dtype=torch.bool, device=sim.torch_device)
    floor[0] = True  # the ground: in every contact of a character lying on it
    lying, high = model.qpos0.copy(), model.qpos0.copy()
    lying[2], lying[3:7] = 0.1, [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]  # on its back, at the floor
    high[2] = 5.0  # far above the floor: no contacts
    sim.set_state(range(4), np.stack([lying, high, lying, high]), np.zeros((4, model.nv)))
    world, geom = sim.contacts()
    assert len(world) > 8 and set(world) == {0, 2}
    np.testing.assert_array_equal(sim.worlds_touching(floor).cpu().numpy(), [True, False, True, False])
    np.testing.assert_array_equal(sim.worlds_touching(torch.zeros_like(floor)).cpu().numpy(), [False] * 4)
    sim.set_state(range(4), np.stack([lying] * 4), np.zeros((4, model.nv)))
    np.testing.assert_array_equal(sim.worlds_touching(floor).cpu().numpy(), [True] * 4)
    sim.set_state([0, 1, 2], np.stack([high] * 3), np.zeros((3, model.nv)))  # the pool keeps rows past the count
    assert set(sim.contacts()[0]) == {3}
    np.testing.assert_array_equal(sim.worlds_touching(floor).cpu().numpy(), [False, False, False, True])
