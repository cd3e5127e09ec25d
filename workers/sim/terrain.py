"""The ground under the character: flat (the floor plane) or a rough MuJoCo height field.

`TerrainConfig` is part of the simulator's config (`SimConfig.terrain`, the run's
`terrain` section). Flat is the default and leaves the model exactly as the
character file has it.

Rough: white noise smoothed by a Gaussian of standard deviation `bump_width`,
whose heights are then spread evenly over [0, roughness] (each grid point's height
is its rank among all of them). Min-max scaling alone would leave 70% of the
ground within a quarter of `roughness` (measured on the default field), the
extremes being a few rare peaks; the rank keeps the bumps' shapes and makes
`roughness` the relief the feet meet.
There is no flat patch at the origin: resets start anywhere along the clips, not
at the origin, and lift the character clear of the bumps instead (`reset_lift`).

In the model (`terrain_model`) the character file's `floor` geom becomes the
height field, in place: same name, id and contact parameters, so
`Character.floor_geom` is the ground in both models. Beyond the field the ground
is a copy of the original floor plane, `floor_beyond`, lowered by
`BEYOND_DROP_M` so that feet on the field's lowest spots seldom reach it too
(they sink a few millimetres; a double contact would stiffen the ground). It comes
second among the geoms: the character's geom ids are one more than in
`Character.model` (look them up by name).

MuJoCo's height field is a triangulated grid: row r lies at y = -size/2 + r·d,
column c at x = -size/2 + c·d (d = size / (n - 1)), and every cell is split
along its diagonal from (r, c) to (r + 1, c + 1). `height_at` interpolates on
the same triangles, so it is the height MuJoCo's ground has under a point.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

from workers.body import rotations as rot

TERRAIN_KINDS = ("flat", "rough")
GROUND_GEOMS = ("floor", "floor_beyond")  # geoms that are the ground (touching them with the feet is no fall)
BEYOND_DROP_M = 0.02  # how far the plane beyond the field lies below the field's lowest point
BASE_M = 0.2  # thickness of the height field's solid below its lowest point


@dataclass
class TerrainConfig:
    # flat: the character file's floor plane; rough: a height field of random bumps under the character.
    kind: str = "flat"
    # Largest height of the bumps (metres) above the lowest point of the field.
    roughness: float = 0.1
    # Seed of the field's bumps (the same seed gives the same ground in every environment and run).
    seed: int = 0
    # Side of the square field (metres), centred at the origin, and its grid spacing (metres).
    # Beyond the field the ground is flat, BEYOND_DROP_M below the field's lowest point.
    size: float = 40.0
    spacing: float = 0.1
    # Width of the bumps (metres): the standard deviation of the Gaussian that smooths the noise.
    bump_width: float = 0.3

    def __post_init__(self) -> None:
        if self.kind not in TERRAIN_KINDS:
            raise ValueError(f"terrain.kind: unknown terrain {self.kind!r}; expected one of {TERRAIN_KINDS}")
        if self.roughness < 0:
            raise ValueError(f"terrain.roughness must be non-negative, got {self.roughness}")
        if self.size <= 0 or self.spacing <= 0 or self.spacing > self.size:
            raise ValueError(
                f"terrain.size and terrain.spacing must be positive, spacing <= size; got {self.size}, {self.spacing}"
            )
        if self.bump_width <= 0:
            raise ValueError(f"terrain.bump_width must be positive, got {self.bump_width}")


def grid_size(config: TerrainConfig) -> int:
    """Points per side of the field's grid; the actual spacing is size / (n - 1)."""
    return int(round(config.size / config.spacing)) + 1


def unit_elevation(config: TerrainConfig) -> np.ndarray:
    """[n, n] the field's heights over roughness: float32 in [0, 1], what MuJoCo stores; read-only."""
    if config.kind == "flat" or config.roughness == 0:
        unit = np.zeros((grid_size(config),) * 2, np.float32)
        unit.setflags(write=False)
        return unit
    return _bumps(config.seed, config.size, grid_size(config), config.bump_width)


@lru_cache(maxsize=4)
def _bumps(seed: int, size: float, n: int, bump_width: float) -> np.ndarray:
    """[n, n] float32 smoothed noise ranked into [0, 1] (min 0 and max 1 exactly), rows along y; read-only."""
    noise = np.random.default_rng(seed).standard_normal((n, n))
    # A Gaussian filter of standard deviation w in space is exp(-2 pi^2 w^2 f^2) in frequency.
    f = np.fft.fftfreq(n, d=size / (n - 1))
    gain = np.exp(-2.0 * (np.pi * bump_width) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    smooth = np.fft.ifft2(np.fft.fft2(noise) * gain).real
    rank = np.empty(n * n)
    rank[np.argsort(smooth, axis=None, kind="stable")] = np.arange(n * n)
    unit = (rank / (n * n - 1)).reshape(n, n).astype(np.float32)
    unit.setflags(write=False)
    return unit


def elevation(config: TerrainConfig) -> np.ndarray:
    """[n, n] heights (metres, in [0, roughness]) of the grid points; row r at y = -size/2 + r·d, column c
    at x = -size/2 + c·d, d = size / (n - 1). Zeros for flat terrain."""
    return config.roughness * unit_elevation(config).astype(np.float64)


def height_at(config: TerrainConfig, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ground height (metres) under points (x, y) of any broadcastable shapes, as MuJoCo's ground has it.

    On the field: linear on MuJoCo's triangles; beyond it: the plane, BEYOND_DROP_M below 0.
    """
    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    if config.kind == "flat":
        return np.zeros(x.shape)
    h = unit_elevation(config)
    n = h.shape[0]
    d = config.size / (n - 1)
    u, v = (x + config.size / 2) / d, (y + config.size / 2) / d  # grid coordinates: column, row
    inside = (u >= 0) & (u <= n - 1) & (v >= 0) & (v <= n - 1)
    c = np.clip(np.floor(u), 0, n - 2).astype(int)
    r = np.clip(np.floor(v), 0, n - 2).astype(int)
    fu, fv = np.clip(u - c, 0, 1), np.clip(v - r, 0, 1)
    h00, h01, h10, h11 = h[r, c], h[r, c + 1], h[r + 1, c], h[r + 1, c + 1]
    # Where fu >= fv: triangle (r, c), (r, c + 1), (r + 1, c + 1); elsewhere (r, c), (r + 1, c), (r + 1, c + 1).
    lower = h00 + fu * (h01 - h00) + fv * (h11 - h01)
    upper = h00 + fv * (h10 - h00) + fu * (h11 - h10)
    return np.where(inside, config.roughness * np.where(fu >= fv, lower, upper), -BEYOND_DROP_M)


# What the plane beyond the field copies from the character file's floor (all but its shape and place).
_FLOOR_ATTRS = (
    "size",
    "contype",
    "conaffinity",
    "condim",
    "priority",
    "friction",
    "solmix",
    "solref",
    "solimp",
    "margin",
    "gap",
    "material",
    "rgba",
    "group",
)


def terrain_model(spec: mujoco.MjSpec, config: TerrainConfig) -> mujoco.MjModel:
    """Compile the character's spec (`Character.spec()`) with the rough ground of config (see the module doc)."""
    if config.kind != "rough":
        raise ValueError(f"terrain_model builds rough terrain; terrain.kind is {config.kind!r}")
    floor = spec.geom("floor")
    beyond = spec.worldbody.add_geom(name="floor_beyond", type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[0, 0, -BEYOND_DROP_M])
    for attr in _FLOOR_ATTRS:
        setattr(beyond, attr, getattr(floor, attr))
    unit = unit_elevation(config)
    half = config.size / 2
    # MuJoCo rescales the data to [0, 1] (already so) and refuses a zero elevation: all-zero data is flat at any.
    spec.add_hfield(
        name="terrain",
        size=[half, half, config.roughness if config.roughness > 0 else 1.0, BASE_M],
        nrow=unit.shape[0],
        ncol=unit.shape[1],
        userdata=unit.ravel(),
    )
    floor.type = mujoco.mjtGeom.mjGEOM_HFIELD
    floor.hfieldname = "terrain"
    return spec.compile()


def ground_geoms(model: mujoco.MjModel) -> list[int]:
    """Ids of the model's geoms that are the ground (the floor, and the plane beyond a rough field)."""
    return [g for g in range(model.ngeom) if model.geom(g).name in GROUND_GEOMS]


def reset_lift(config: TerrainConfig, model: mujoco.MjModel, xpos: np.ndarray, xquat: np.ndarray) -> np.ndarray:
    """[N] how far to raise each character so that none of its geoms starts below the ground.

    xpos [N, B, 3], xquat [N, B, 4]: the character's bodies (without the world) in the pose to start
    from, a reference frame recorded on flat ground. Each geom is sampled at 27 points (a box at its
    corners, edge and face midpoints and centre; a capsule along its axis, each point with the radius;
    a sphere at its centre with the radius; other shapes by their bounding sphere), and the lift is the
    largest depth of a sample's bottom below the ground under it, or 0.
    """
    geoms = np.flatnonzero(model.geom_bodyid > 0)
    kind, size = model.geom_type[geoms], model.geom_size[geoms]
    half, radius = np.zeros((len(geoms), 3)), model.geom_rbound[geoms].copy()
    box, capsule = kind == mujoco.mjtGeom.mjGEOM_BOX, kind == mujoco.mjtGeom.mjGEOM_CAPSULE
    half[box], radius[box] = size[box], 0.0
    half[capsule, 2] = size[capsule, 1]
    round_ = capsule | (kind == mujoco.mjtGeom.mjGEOM_SPHERE)
    radius[round_] = size[round_, 0]
    lattice = np.stack(np.meshgrid(*[[-1.0, 0.0, 1.0]] * 3, indexing="ij"), -1).reshape(-1, 3)  # [27, 3]
    geom_rot = rot.to_matrix(model.geom_quat[geoms])
    in_body = model.geom_pos[geoms, None] + (lattice * half[:, None]) @ geom_rot.swapaxes(-1, -2)  # [G, 27, 3]
    body = model.geom_bodyid[geoms] - 1
    points = xpos[:, body, None] + in_body @ rot.to_matrix(xquat[:, body]).swapaxes(-1, -2)  # [N, G, 27, 3]
    depth = height_at(config, points[..., 0], points[..., 1]) - (points[..., 2] - radius[:, None])
    return np.maximum(depth.reshape(len(points), -1).max(axis=1), 0.0)
