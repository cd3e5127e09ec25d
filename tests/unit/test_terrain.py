"""Rough terrain: the height field, the ground height under points, resets and falls on it."""

import mujoco
import numpy as np
import pytest

from workers.body.features import StateLayout
from workers.sim.env import BatchedSim, SimConfig
from workers.sim.terrain import (
    BEYOND_DROP_M,
    TerrainConfig,
    elevation,
    ground_geoms,
    height_at,
    reset_lift,
    terrain_model,
)

ROUGH = TerrainConfig(kind="rough", roughness=0.1, seed=1)


def ray_down(model: mujoco.MjModel, data: mujoco.MjData, x: float, y: float, top: float = 2.0) -> float:
    """Height of the first static geom straight below (x, y), by MuJoCo's ray."""
    geom = np.zeros(1, np.int32)
    return top - mujoco.mj_ray(model, data, np.array([x, y, top]), np.array([0.0, 0.0, -1.0]), None, 1, -1, geom)


def ground_points(sim: BatchedSim, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Environment i's contacts with the ground: where they touch the ground [C, 3] and their normals [C, 3]
    pointing out of the ground."""
    contact = sim.get_data(i).contact  # ncon long
    # The normal points from geom 0 to geom 1; pos lies midway between the surfaces, dist apart.
    sign = np.where(np.isin(contact.geom[:, 0], ground_geoms(sim.model)), 1.0, -1.0)
    normals = sign[:, None] * contact.frame[:, :3]
    return contact.pos - normals * contact.dist[:, None] / 2, normals


def test_height_at_matches_mujoco_rays(character):
    config = TerrainConfig(kind="rough", roughness=0.2, seed=3, size=4.0, spacing=0.1)
    model = terrain_model(character.spec(), config)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    # Random points on the field and beyond it (the plane BEYOND_DROP_M below), and the grid's own points.
    xy = np.random.default_rng(0).uniform(-2.5, 2.5, (300, 2))
    xy = np.concatenate((xy, np.stack(np.meshgrid([-2.0, -0.3, 1.1], [-1.7, 0.0, 2.0]), -1).reshape(-1, 2)))
    rays = np.array([ray_down(model, data, x, y) for x, y in xy])
    np.testing.assert_allclose(height_at(config, xy[:, 0], xy[:, 1]), rays, atol=1e-6)
    assert np.isclose(height_at(config, 2.3, 0.0), -BEYOND_DROP_M)
    # Known answer: at a cell's centre the height is the middle of MuJoCo's diagonal from (r, c) to
    # (r + 1, c + 1), not the mean of the four corners. Cell (r, c) = (10, 20) spans x in [0, 0.1], y in [-1, -0.9].
    h = elevation(config)
    assert np.isclose(height_at(config, 0.05, -0.95), (h[10, 20] + h[11, 21]) / 2)
    assert np.isclose(height_at(config, 0.0, -1.0), h[10, 20])
    # The character's own model is untouched; the rough one has its geoms, the floor a height field.
    assert character.model.geom_type[character.floor_geom] == mujoco.mjtGeom.mjGEOM_PLANE
    assert model.geom_type[character.floor_geom] == mujoco.mjtGeom.mjGEOM_HFIELD
    assert [model.geom(g).name for g in ground_geoms(model)] == ["floor", "floor_beyond"]
    names = [model.geom(g).name for g in range(model.ngeom) if g not in ground_geoms(model)]
    assert names == [character.model.geom(g).name for g in range(1, character.model.ngeom)]


def test_grid_is_seeded_and_spans_roughness():
    h = elevation(ROUGH)
    assert h.shape == (401, 401)  # 40 m at 0.1 m, both ends included
    np.testing.assert_array_equal(h, elevation(TerrainConfig(kind="rough", roughness=0.1, seed=1)))
    assert not np.array_equal(h, elevation(TerrainConfig(kind="rough", roughness=0.1, seed=2)))
    assert h.min() == 0.0 and np.isclose(h.max(), 0.1)
    # Spread evenly over [0, roughness] (ranked), and smooth: neighbours differ by a few millimetres.
    np.testing.assert_allclose(np.percentile(h, [25, 50, 75]), [0.025, 0.05, 0.075], atol=1e-3)
    assert np.abs(np.diff(h, axis=0)).mean() < 0.01 and np.abs(np.diff(h, axis=1)).mean() < 0.01
    np.testing.assert_array_equal(elevation(TerrainConfig()), 0.0)
    np.testing.assert_array_equal(height_at(TerrainConfig(), [1.0, -30.0], [2.0, 0.0]), 0.0)


def test_flat_terrain_is_unchanged(character, walk_run):
    def run(config):
        sim = BatchedSim(character, walk_run, num_envs=4, config=config, seed=3)
        assert sim.model is character.model
        rng = np.random.default_rng(0)
        out = [sim.reset()]
        for _ in range(30):  # long enough for falls and resets
            r = sim.step(rng.normal(0, 0.3, (4, 28)))
            out += [r.state, r.kin.qpos, r.fell, sim.qacc_warmstart.copy()]
            out.append(sim.reset(np.flatnonzero(r.done)))
        return out

    default = run(SimConfig())
    flat = run(SimConfig(terrain=TerrainConfig(kind="flat", roughness=0.3, seed=7)))
    for a, b in zip(default, flat, strict=True):
        np.testing.assert_array_equal(a, b)


def test_resets_start_clear_of_the_bumps(character, walk_run):
    flat = BatchedSim(character, walk_run, num_envs=16, seed=0)
    rough = BatchedSim(character, walk_run, num_envs=16, config=SimConfig(terrain=ROUGH), seed=0)
    np.testing.assert_array_equal(rough.clip_id, flat.clip_id)
    before, after = flat.kin_state(), rough.kin_state()
    lift = after.xpos[:, 0, 2] - before.xpos[:, 0, 2]
    # Each character is raised by the depth of its deepest sample below the ground (the flat sim holds the
    # reference pose), so that it just touches the ground and is nowhere inside it.
    np.testing.assert_allclose(lift, reset_lift(ROUGH, rough.model, before.xpos, before.xquat), atol=1e-12)
    # Characters in flight (running) high enough over the bumps stay where they were; none is raised by more
    # than the bumps' height plus how far its reference pose dips below flat ground (a foot a centimetre or
    # two into the floor; which starts are drawn depends on the library's start weights).
    dip = reset_lift(TerrainConfig(kind="rough", roughness=0.0), rough.model, before.xpos, before.xquat)
    assert (lift >= 0).all() and (lift > 0).sum() >= 8 and (lift <= ROUGH.roughness + dip + 1e-9).all()
    np.testing.assert_allclose(reset_lift(ROUGH, rough.model, after.xpos, after.xquat), 0.0, atol=1e-9)
    assert all((rough.get_data(i).contact.dist > -1e-9).all() for i in range(16))  # touching at most
    # The returned states are the raised reference's: heights up by the lift, everything else the same.
    states = rough.reset(np.arange(16), flat.clip_id, flat.start_frame)
    expected = walk_run.features(flat.clip_id, flat.start_frame)
    expected[:, StateLayout(character.num_bodies).height] += lift[:, None]
    np.testing.assert_allclose(states, expected, atol=1e-5)


def test_feet_touch_the_ground_where_height_at_has_it(character, walk_run):
    flat = BatchedSim(character, walk_run, num_envs=4, seed=0)
    rough = BatchedSim(character, walk_run, num_envs=4, config=SimConfig(terrain=ROUGH), seed=0)
    heights = {"flat": [], "rough": []}
    for _ in range(8):
        actions = character.qpos_to_action(flat.reference_state().qpos)
        for name, sim in (("flat", flat), ("rough", rough)):
            sim.step(actions)
            for i in range(4):
                points, normals = ground_points(sim, i)
                # Contacts pushing up touch the ground surface exactly (MuJoCo's height field also makes a few
                # sideways contacts on its cells' edges, below the surface).
                up = normals[:, 2] > 0.9
                expected = height_at(sim.config.terrain, points[up, 0], points[up, 1])
                np.testing.assert_allclose(points[up, 2], expected, atol=1e-6)
                heights[name] += list(points[up, 2])
    assert len(heights["flat"]) > 10 and len(heights["rough"]) > 10
    np.testing.assert_allclose(heights["flat"], 0.0, atol=1e-9)
    assert np.ptp(heights["rough"]) > 0.02  # the feet met bumps of different heights


def test_falls_are_detected_exactly_on_rough_terrain(character, walk_run):
    config = SimConfig(tracking_error_m=0, end_on_fall=False, terrain=ROUGH)
    sim = BatchedSim(character, walk_run, num_envs=4, config=config, seed=0)
    assert sim._floor_test is None  # the height field is no plane: every contact list is read
    assert not sim._fall_geom[ground_geoms(sim.model)].any()  # the field and the plane beyond it are ground
    fell = np.zeros(4, bool)
    for _ in range(60):
        # Servos holding the zero pose from mid-stride: without balance the character topples.
        r = sim.step(np.zeros((4, 28)))
        contacts = [sim.get_data(i) for i in range(4)]
        expected = [d.ncon > 0 and bool(sim._fall_geom[d.contact.geom].any()) for d in contacts]
        np.testing.assert_array_equal(r.fell, expected)
        fell |= r.fell
    assert fell.all()
    assert sim.kin_state().xpos[:, 0, 2].max() < 0.6 + 0.1  # lying on the bumps


@pytest.mark.parametrize(
    "key, value",
    [("kind", "hilly"), ("roughness", -0.1), ("size", 0.0), ("spacing", -1.0), ("bump_width", 0.0)],
)
def test_config_rejects_bad_values(key, value):
    with pytest.raises(ValueError, match=f"terrain.{key}"):
        TerrainConfig(**{key: value})


def test_rough_terrain_needs_a_free_root(walk_run):
    from workers.body.character import Character

    fixed = Character.load(fixed_root=True, root_height=2.0)
    with pytest.raises(ValueError, match="free root"):
        BatchedSim(fixed, walk_run, num_envs=1, config=SimConfig(terrain=ROUGH))
