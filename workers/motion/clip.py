"""Clips in the character's generalised coordinates, at their source rate and processed.

A `RawClip` is what a file format loader returns: root position, root and joint
rotations as MuJoCo qpos of our character (z-up), with the time of each frame.
`process` turns it into a `MotionClip` at the control rate: resampled (slerp for
rotations), velocities by finite differences (MuJoCo's own mj_differentiatePos),
and every body's position, rotation, linear and angular velocity by MuJoCo's
forward kinematics on our MJCF, so that reference and simulated states share one
definition.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields, replace

import mujoco
import numpy as np

from workers.body import rotations as rot
from workers.body.character import Character
from workers.motion.errors import ClipError

log = logging.getLogger(__name__)


@dataclass
class RawClip:
    """Poses at the source rate.

    name: a short name (`humanoid3d_walk`).
    qpos: [T, nq] generalised coordinates of our character, z-up, metres.
    times: [T] seconds since the first frame, strictly increasing.
    loop: the clip is cyclic; for a cyclic clip the last frame is the first pose
      of the next cycle (DeepMimic's convention), so the period is times[-1].
    source: the file it came from.
    """

    name: str
    qpos: np.ndarray
    times: np.ndarray
    loop: bool
    source: str = ""

    @property
    def duration(self) -> float:
        return float(self.times[-1])


@dataclass
class MotionClip:
    """A clip at the control rate with its full kinematics. Shapes: K frames, B bodies.

    For a cyclic clip, frame K (one past the end) is frame 0 moved by the cycle
    transform: a rotation by `cycle_yaw` about z and a horizontal translation
    `cycle_shift`, so a loop carries the root displacement (and heading) over.
    """

    name: str
    dt: float
    loop: bool
    qpos: np.ndarray  # [K, nq]
    qvel: np.ndarray  # [K, nv]
    xpos: np.ndarray  # [K, B, 3] body origins, world
    xquat: np.ndarray  # [K, B, 4] body rotations, world
    lin_vel: np.ndarray  # [K, B, 3] body-origin linear velocity, world
    ang_vel: np.ndarray  # [K, B, 3] body angular velocity, world
    foot_min_z: np.ndarray  # [K] lowest point of the foot geoms
    cycle_yaw: float = 0.0
    cycle_shift: np.ndarray = None  # [3], z = 0
    source: str = ""

    def __post_init__(self) -> None:
        if self.cycle_shift is None:
            self.cycle_shift = np.zeros(3)

    @property
    def num_frames(self) -> int:
        return self.qpos.shape[0]

    @property
    def duration(self) -> float:
        return self.num_frames * self.dt if self.loop else (self.num_frames - 1) * self.dt

    def to_npz_dict(self) -> dict[str, np.ndarray]:
        return {f.name: np.asarray(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_npz_dict(cls, d) -> MotionClip:
        kw = {f.name: d[f.name] for f in fields(cls)}
        for key in ("name", "source"):
            kw[key] = str(kw[key])
        kw["dt"], kw["cycle_yaw"] = float(kw["dt"]), float(kw["cycle_yaw"])
        kw["loop"] = bool(kw["loop"])
        return cls(**kw)


# ----------------------------------------------------------------------------
# Validation shared by every format
# ----------------------------------------------------------------------------
# The bundled DeepMimic clips carry quaternions whose norms are off by up to 0.42
# (humanoid3d_kick, frame 0; DeepMimic normalises on load), so anything within
# this tolerance is normalised, with a log line, and only norms beyond it (zeros,
# garbage, a column shifted into a quaternion) are refused.
QUAT_NORM_TOL = 0.5


def validate_raw(character: Character, raw: RawClip) -> None:
    """Raise ClipError naming the frame for NaN, non-unit quaternions or bad times."""
    nq = character.model.nq
    if raw.qpos.ndim != 2 or raw.qpos.shape[0] == 0:
        raise ClipError(raw.source or raw.name, "no frames")
    if raw.qpos.shape[1] != nq:
        raise ClipError(raw.source or raw.name, f"expected {nq} coordinates a frame, got {raw.qpos.shape[1]}")
    bad = ~np.isfinite(raw.qpos).all(axis=1)
    if bad.any():
        raise ClipError(raw.source, "non-finite value (NaN or inf)", int(np.argmax(bad)))
    norms = np.linalg.norm(raw.qpos[:, _quat_indices(character)], axis=-1)  # [T, n_quat]
    off = np.abs(norms - 1.0) > QUAT_NORM_TOL
    if off.any():
        frame, k = np.argwhere(off)[0]
        names = ["root"] + [n for n, t in zip(character.joint_names, character.joint_types, strict=True) if t == "ball"]
        joint = names[k]
        raise ClipError(raw.source, f"non-unit quaternion for {joint} (norm {norms[frame, k]:.4f})", int(frame))
    n_off = int((np.abs(norms - 1.0) > 1e-3).sum())
    if n_off:
        log.info("%s: normalised %d quaternions whose norms were off by more than 1e-3", raw.source, n_off)
    if len(raw.times) != raw.qpos.shape[0]:
        raise ClipError(raw.source, "times and frames differ in length")
    steps = np.diff(raw.times)
    if (steps <= 0).any():
        raise ClipError(raw.source, "frame duration must be positive", int(np.argmax(steps <= 0)))
    if raw.loop and raw.qpos.shape[0] < 2:
        raise ClipError(raw.source, "a cyclic clip needs at least two frames")
    check_plausible(character, raw)


# ----------------------------------------------------------------------------
# Plausibility: finite values that no recording of a person has
# ----------------------------------------------------------------------------
# Over every bundled clip (`python -m orchestrator.motion list`) at its source rate, the root stays
# within 3 m of the origin and of its first frame, moves at most 5.3 m/s (humanoid3d_roll) and turns at
# most 12.3 rad/s (humanoid3d_roll); the fastest joint turns at 30.5 rad/s (left shoulder,
# humanoid3d_backflip, 16 Hz). The limits sit well beyond that and beyond what people do, so that only
# broken data is refused: a root in the wrong unit or from a garbled column, a frame of another clip.
MAX_ROOT_DISTANCE_M = 1000.0  # from the origin: a root kilometres away is a unit or parsing error
MAX_ROOT_TRAVEL_M = 100.0  # from the clip's first frame: more than any capture volume (cut longer takes)
MAX_ROOT_SPEED_M_S = 30.0  # between frames; sprinters peak near 12 m/s
# Between frames, for every ball joint (the norm of its angular velocity), hinge and the root's rotation.
# People reach about 40 rad/s at the elbow when throwing; only the shoulder's internal rotation in a
# pitch (~120 rad/s for milliseconds) is faster, and a capture of it at 100 Hz or more would be refused.
MAX_JOINT_SPEED_RAD_S = 50.0


def check_plausible(character: Character, raw: RawClip) -> None:
    """Raise ClipError naming the frame where the root is too far away, or the root or a joint moves
    faster than any person (the limits above; speeds are finite differences between source frames)."""
    if character.root_dofs:
        root = raw.qpos[:, :3]
        for limit, distance, what in (
            (MAX_ROOT_DISTANCE_M, np.linalg.norm(root, axis=1), "from the origin"),
            (MAX_ROOT_TRAVEL_M, np.linalg.norm(root - root[0], axis=1), "from its position in frame 0"),
        ):
            if (distance > limit).any():
                frame = int(np.argmax(distance > limit))
                raise ClipError(raw.source, f"root is {distance[frame]:.3g} m {what} (more than {limit:g} m)", frame)
    if raw.qpos.shape[0] < 2:
        return
    qpos = normalize_quats(character, raw.qpos)
    qvel = np.zeros((qpos.shape[0] - 1, character.model.nv))  # [T - 1, nv]: frame t to t + 1
    for t, dt in enumerate(np.diff(raw.times)):
        mujoco.mj_differentiatePos(character.model, qvel[t], dt, qpos[t], qpos[t + 1])
    # (what, speed [T - 1], limit, unit) for the root's translation and rotation and every joint.
    checks = []
    if character.root_dofs:
        checks.append(("root moves", np.linalg.norm(qvel[:, :3], axis=1), MAX_ROOT_SPEED_M_S, "m/s"))
        checks.append(("root turns", np.linalg.norm(qvel[:, 3:6], axis=1), MAX_JOINT_SPEED_RAD_S, "rad/s"))
    for name, dofs in zip(character.joint_names, character.joint_dof, strict=True):
        checks.append((f"{name} turns", np.linalg.norm(qvel[:, dofs], axis=1), MAX_JOINT_SPEED_RAD_S, "rad/s"))
    over = np.stack([speed > limit for _, speed, limit, _ in checks], axis=1)  # [T - 1, checks]
    if over.any():
        t, k = np.argwhere(over)[0]
        what, speed, limit, unit = checks[k]
        raise ClipError(
            raw.source,
            f"{what} at {speed[t]:.3g} {unit} from frame {t} (more than {limit:g} {unit})",
            int(t) + 1,
        )


# ----------------------------------------------------------------------------
# Resampling, mirroring, cycle transform
# ----------------------------------------------------------------------------
def _quat_indices(character: Character) -> np.ndarray:
    return np.concatenate(([np.arange(3, 7)], character.ball_qpos))  # [n_quat, 4]


def normalize_quats(character: Character, qpos: np.ndarray) -> np.ndarray:
    out = qpos.copy()
    qi = _quat_indices(character)
    out[..., qi] = rot.normalize(qpos[..., qi])
    return out


def interpolate_qpos(character: Character, raw: RawClip, t: np.ndarray) -> np.ndarray:
    """qpos [len(t), nq] at times t (clamped to the clip): lerp positions and hinges, slerp quats."""
    t = np.clip(t, raw.times[0], raw.times[-1])
    if len(raw.times) == 1:
        return np.repeat(raw.qpos[:1], len(t), axis=0)
    i = np.clip(np.searchsorted(raw.times, t, side="right") - 1, 0, len(raw.times) - 2)
    a = (t - raw.times[i]) / (raw.times[i + 1] - raw.times[i])
    q0, q1 = raw.qpos[i], raw.qpos[i + 1]
    out = q0 + a[:, None] * (q1 - q0)
    qi = _quat_indices(character)
    out[:, qi] = rot.slerp(q0[:, qi], q1[:, qi], a[:, None])
    return out


def cycle_transform(raw: RawClip) -> tuple[float, np.ndarray]:
    """(yaw, shift) of the rigid motion that takes the first root pose to the last."""
    q0, q1 = raw.qpos[0], raw.qpos[-1]
    dyaw = float(rot.yaw(q1[3:7]) - rot.yaw(q0[3:7]))
    dyaw = (dyaw + np.pi) % (2 * np.pi) - np.pi
    shift = q1[:3] - rot.yaw_matrix(dyaw) @ q0[:3]
    shift[2] = 0.0
    return dyaw, shift


def transform_qpos(qpos: np.ndarray, yaw: np.ndarray | float, shift: np.ndarray) -> np.ndarray:
    """Apply a rotation about z by yaw [...] then a translation shift [..., 3] to root coordinates."""
    out = qpos.copy()
    out[..., :3] = np.einsum("...ij,...j->...i", rot.yaw_matrix(np.asarray(yaw)), qpos[..., :3]) + shift
    out[..., 3:7] = rot.mul(rot.from_yaw(np.asarray(yaw)), qpos[..., 3:7])
    return out


def mirror_qpos(character: Character, qpos: np.ndarray) -> np.ndarray:
    """Reflect poses [..., nq] across the sagittal (x-z) plane and swap left and right.

    A rotation R becomes M R M with M = diag(1, -1, 1), i.e. (w, x, y, z) -> (w, -x, y, -z);
    hinges about the y axis keep their angle. Mirroring twice is the identity.
    """
    out = qpos.copy()
    out[..., 1] = -qpos[..., 1]
    flip = np.array([1.0, -1.0, 1.0, -1.0])
    out[..., 3:7] = qpos[..., 3:7] * flip
    perm = character.joint_mirror_perm()
    for j, src in enumerate(perm):
        dst_sl, src_sl = character.joint_qpos[j], character.joint_qpos[src]
        val = qpos[..., src_sl]
        out[..., dst_sl] = val * flip if character.joint_types[j] == "ball" else val
    return out


def mirror_raw(character: Character, raw: RawClip) -> RawClip:
    return replace(raw, name=raw.name + "_mirror", qpos=mirror_qpos(character, raw.qpos))


# ----------------------------------------------------------------------------
# Processing
# ----------------------------------------------------------------------------
def process(character: Character, raw: RawClip, fps: float) -> MotionClip:
    """Resample to `fps` and compute the full kinematics with MuJoCo.

    A cyclic clip of period P is resampled to K = round(P * fps) frames spaced
    exactly P / K apart (within half a frame of 1 / fps), so that it repeats
    seamlessly at the control rate; a one-shot clip gets frames at exactly 1 / fps, the last
    one kept when the clip falls short of it by less than its frame time's rounding could make
    it: files store a rounded frame time (a BVH's 0.033333 s makes 454 frames 15.133182 s
    long, 0.005 of a frame short of 454 / 30 s), at most 1.5e-5 of it at six decimals and
    30 Hz, so 1e-4 of the clip's length (plus 1e-3 of a frame, at most half a frame) is let go.
    """
    validate_raw(character, raw)
    if raw.loop:
        period = raw.duration
        k = max(1, int(round(period * fps)))
        dt = period / k
        times = np.arange(k) * dt
        yaw, shift = cycle_transform(raw)
    else:
        dt = 1.0 / fps
        frames = raw.duration * fps
        k = int(np.floor(frames + min(0.5, 1e-3 + 1e-4 * frames))) + 1
        times = np.arange(k) * dt
        yaw, shift = 0.0, np.zeros(3)
    raw = replace(raw, qpos=normalize_quats(character, raw.qpos))
    qpos = interpolate_qpos(character, raw, times)  # slerp keeps quaternions unit
    if raw.loop:
        next_first = transform_qpos(qpos[0], yaw, shift)
        nxt = np.concatenate((qpos[1:], next_first[None]), axis=0)
    else:
        nxt = qpos[1:]
    qvel = finite_difference_qvel(character.model, qpos, nxt, dt)
    kin = forward_kinematics(character, qpos, qvel)
    return MotionClip(
        name=raw.name, dt=dt, loop=raw.loop, qpos=qpos, qvel=qvel, **kin,
        cycle_yaw=yaw, cycle_shift=shift, source=raw.source,
    )  # fmt: skip


def finite_difference_qvel(model: mujoco.MjModel, qpos: np.ndarray, nxt: np.ndarray, dt: float) -> np.ndarray:
    """Forward differences: qvel[t] takes qpos[t] to nxt[t] in dt (MuJoCo's own integration).

    nxt has K or K - 1 rows; without a successor the last frame repeats its predecessor's velocity.
    """
    k = qpos.shape[0]
    qvel = np.zeros((k, model.nv))
    for t in range(nxt.shape[0]):
        mujoco.mj_differentiatePos(model, qvel[t], dt, qpos[t], nxt[t])
    if nxt.shape[0] < k and k > 1:
        qvel[-1] = qvel[-2]
    return qvel


def forward_kinematics(character: Character, qpos: np.ndarray, qvel: np.ndarray) -> dict[str, np.ndarray]:
    """Body positions, rotations and velocities, and the feet's lowest point, for each frame."""
    model = character.model
    data = mujoco.MjData(model)
    k, nb = qpos.shape[0], character.num_bodies
    out = {
        "xpos": np.zeros((k, nb, 3)),
        "xquat": np.zeros((k, nb, 4)),
        "lin_vel": np.zeros((k, nb, 3)),
        "ang_vel": np.zeros((k, nb, 3)),
        "foot_min_z": np.zeros(k),
    }
    feet = character.foot_geoms
    for t in range(k):
        data.qpos[:] = qpos[t]
        data.qvel[:] = qvel[t]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        mujoco.mj_comVel(model, data)
        out["xpos"][t] = data.xpos[1:]
        out["xquat"][t] = data.xquat[1:]
        w = data.cvel[1:, :3]
        out["ang_vel"][t] = w
        out["lin_vel"][t] = data.cvel[1:, 3:] + np.cross(w, data.xpos[1:] - data.subtree_com[1])
        out["foot_min_z"][t] = geom_min_z(model, data, feet)
    return out


def geom_min_z(model: mujoco.MjModel, data: mujoco.MjData, geoms: np.ndarray) -> float:
    """Lowest point of the given geoms (boxes by their corners, spheres and capsules exactly)."""
    low = np.inf
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    for g in geoms:
        size, pos, mat = model.geom_size[g], data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
        gtype = model.geom_type[g]
        if gtype == mujoco.mjtGeom.mjGEOM_BOX:
            z = pos[2] + (corners * size) @ mat[2]
            low = min(low, float(z.min()))
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            low = min(low, pos[2] - size[0])
        elif gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            low = min(low, pos[2] - abs(mat[2, 2]) * size[1] - size[0])
        else:
            low = min(low, pos[2] - model.geom_rbound[g])
    return low
