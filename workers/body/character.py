"""The humanoid: its MJCF model and the index tables everything else uses.

`Character` is built once from the MJCF and holds the names and index arrays of
bodies, joints and actuators, so that clip loaders, state features and the
simulator address the model by name, never by hard-coded offsets.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from workers.body import rotations as rot

ASSET_DIR = Path(__file__).parent / "assets"
HUMANOID_XML = ASSET_DIR / "humanoid.xml"

# What the code addresses by name (clip formats, state features, falls, mirroring): a character file
# must have these bodies and joints, of these types, with one actuator per actuated degree of freedom.
SKELETON_BODIES = [
    "root", "chest", "neck",
    "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow", "left_wrist",
    "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
]  # fmt: skip
SKELETON_JOINTS = {
    "chest": "ball", "neck": "ball",
    "right_hip": "ball", "right_knee": "hinge", "right_ankle": "ball",
    "right_shoulder": "ball", "right_elbow": "hinge",
    "left_hip": "ball", "left_knee": "hinge", "left_ankle": "ball",
    "left_shoulder": "ball", "left_elbow": "hinge",
}  # fmt: skip
SKELETON_GEOMS = ["floor", "right_ankle", "left_ankle"]  # the ground and the feet


class CharacterError(ValueError):
    """A character file that cannot be used: missing, not an MJCF, or not our humanoid's skeleton."""

    def __init__(self, path: object, message: str):
        self.path = str(path)
        self.message = message
        super().__init__(f"{self.path}: {message}")


# Left/right counterparts; every name not listed is its own mirror.
_MIRROR_PAIRS = [
    ("right_hip", "left_hip"),
    ("right_knee", "left_knee"),
    ("right_ankle", "left_ankle"),
    ("right_shoulder", "left_shoulder"),
    ("right_elbow", "left_elbow"),
    ("right_wrist", "left_wrist"),
]


def mirror_name(name: str) -> str:
    for a, b in _MIRROR_PAIRS:
        if name == a:
            return b
        if name == b:
            return a
    return name


def build_spec(
    xml_path: str | Path = HUMANOID_XML,
    sim_hz: float = 480.0,
    self_collision: bool = False,
    fixed_root: bool = False,
    root_height: float | None = None,
) -> mujoco.MjSpec:
    """The character's model before compilation (what `build_model` compiles).

    Args:
      xml_path: the MJCF file.
      sim_hz: physics rate; the timestep is 1 / sim_hz.
      self_collision: let the character's own geoms collide with each other
        (parents and children never do).
      fixed_root: weld the root to the world (no free joint), for PD tests.
      root_height: with fixed_root, where the root is welded.
    """
    if sim_hz <= 0:
        raise ValueError(f"sim_hz must be positive, got {sim_hz}")
    spec = mujoco.MjSpec.from_file(str(xml_path))
    spec.option.timestep = 1.0 / sim_hz
    root = spec.body("root")
    if fixed_root:
        spec.delete(spec.joint("root"))
        if root_height is not None:
            root.pos = [0.0, 0.0, root_height]
    if self_collision:
        for geom in spec.geoms:
            if geom.name != "floor":
                geom.conaffinity = 1
    return spec


def build_model(xml_path: str | Path = HUMANOID_XML, **build_kwargs) -> mujoco.MjModel:
    """Compile the character; the arguments are `build_spec`'s."""
    return build_spec(xml_path, **build_kwargs).compile()


@dataclass
class Character:
    """Names and index tables of the compiled humanoid.

    Bodies are the model's bodies without the world (15). Joints are the
    actuated joints in qpos order: ball joints take 4 qpos (a quaternion) and 3
    dofs, hinges 1 and 1. Actions are the 28 actuator targets, in actuator order,
    which is the dof order of the actuated joints (rotation-vector components for
    ball joints, angles for hinges).
    """

    model: mujoco.MjModel
    body_names: list[str]
    joint_names: list[str]
    joint_types: list[str]  # "ball" | "hinge"
    joint_qpos: list[slice]
    joint_dof: list[slice]
    body_of_joint: np.ndarray  # [J] body index (0-based, without world) each joint drives
    foot_geoms: np.ndarray  # geom ids allowed to touch the ground
    foot_bodies: np.ndarray  # body indices of the feet
    hand_bodies: np.ndarray
    head_body: int
    floor_geom: int
    xml_hash: str
    root_dofs: int = 6  # 0 when the root is welded (fixed_root=True)
    # build_spec's arguments that made `model`, so that variants of it can be built (`spec()`).
    build_args: dict = field(default_factory=dict)
    ball_qpos: np.ndarray = field(init=False)  # [n_ball, 4] qpos indices of ball quats
    hinge_qpos: np.ndarray = field(init=False)  # [n_hinge] qpos index of each hinge
    ball_act: np.ndarray = field(init=False)  # [n_ball, 3] action indices
    hinge_act: np.ndarray = field(init=False)  # [n_hinge]

    def __post_init__(self) -> None:
        balls = [i for i, t in enumerate(self.joint_types) if t == "ball"]
        hinges = [i for i, t in enumerate(self.joint_types) if t == "hinge"]
        self.ball_qpos = np.array([np.arange(4) + self.joint_qpos[i].start for i in balls])
        self.hinge_qpos = np.array([self.joint_qpos[i].start for i in hinges])
        dof0 = self.root_dofs  # the free root's dofs come first; actions skip them
        self.ball_act = np.array([np.arange(3) + self.joint_dof[i].start - dof0 for i in balls])
        self.hinge_act = np.array([self.joint_dof[i].start - dof0 for i in hinges])

    @classmethod
    def load(cls, xml_path: str | Path = HUMANOID_XML, **build_kwargs) -> Character:
        """The character of an MJCF file; CharacterError naming the file if it is missing, does not
        compile, or is not our humanoid's skeleton (`SKELETON_*`)."""
        path = Path(xml_path)
        if problem := file_problem(path):
            raise CharacterError(path, problem)
        try:
            model = build_model(xml_path, **build_kwargs)
        except ValueError as e:  # MuJoCo's parser and compiler errors
            raise CharacterError(path, f"not a loadable MJCF ({_one_line(e)})") from None
        _check_skeleton(path, model, build_kwargs.get("fixed_root", False))
        body_names = [model.body(i).name for i in range(1, model.nbody)]
        joint_names, joint_types, joint_qpos, joint_dof, body_of_joint = [], [], [], [], []
        for j in range(model.njnt):
            jtype = int(model.jnt_type[j])
            if jtype == mujoco.mjtJoint.mjJNT_FREE:
                continue
            kind = {int(mujoco.mjtJoint.mjJNT_BALL): "ball", int(mujoco.mjtJoint.mjJNT_HINGE): "hinge"}[jtype]
            nq, nv = (4, 3) if kind == "ball" else (1, 1)
            qa, da = model.jnt_qposadr[j], model.jnt_dofadr[j]
            joint_names.append(model.joint(j).name)
            joint_types.append(kind)
            joint_qpos.append(slice(qa, qa + nq))
            joint_dof.append(slice(da, da + nv))
            body_of_joint.append(model.jnt_bodyid[j] - 1)
        root_dofs = 6 if int(mujoco.mjtJoint.mjJNT_FREE) in model.jnt_type.tolist() else 0
        try:
            _check_actuators(model, joint_names, joint_dof, root_dofs)
        except ValueError as e:
            raise CharacterError(path, str(e)) from None
        foot_names = ["right_ankle", "left_ankle"]
        return cls(
            model=model,
            body_names=body_names,
            joint_names=joint_names,
            joint_types=joint_types,
            joint_qpos=joint_qpos,
            joint_dof=joint_dof,
            body_of_joint=np.array(body_of_joint),
            foot_geoms=np.array([model.geom(n).id for n in foot_names]),
            foot_bodies=np.array([body_names.index(n) for n in foot_names]),
            hand_bodies=np.array([body_names.index(n) for n in ("right_wrist", "left_wrist")]),
            head_body=body_names.index("neck"),
            floor_geom=model.geom("floor").id,
            xml_hash=hashlib.sha1(Path(xml_path).read_bytes()).hexdigest()[:12],
            root_dofs=root_dofs,
            build_args={"xml_path": str(xml_path), **build_kwargs},
        )

    def spec(self) -> mujoco.MjSpec:
        """A fresh uncompiled copy of the character's model, for variants of it (rough terrain)."""
        return build_spec(**self.build_args)

    # Sizes -------------------------------------------------------------------
    @property
    def num_bodies(self) -> int:
        return len(self.body_names)

    @property
    def num_actions(self) -> int:
        return self.model.nu

    @property
    def end_effectors(self) -> np.ndarray:
        """Hands and feet, AMP's end-effectors."""
        return np.concatenate((self.hand_bodies, self.foot_bodies))

    # Mirroring ---------------------------------------------------------------
    def body_mirror_perm(self) -> np.ndarray:
        """perm[i] is the body whose mirror image body i is."""
        return np.array([self.body_names.index(mirror_name(n)) for n in self.body_names])

    def joint_mirror_perm(self) -> np.ndarray:
        return np.array([self.joint_names.index(mirror_name(n)) for n in self.joint_names])

    # Conversions between actions and joint rotations -------------------------
    def qpos_to_action(self, qpos: np.ndarray) -> np.ndarray:
        """The PD targets [..., 28] that hold the joint rotations of qpos [..., nq]."""
        action = np.zeros(qpos.shape[:-1] + (self.num_actions,))
        action[..., self.ball_act] = rot.to_expmap(qpos[..., self.ball_qpos])
        action[..., self.hinge_act] = qpos[..., self.hinge_qpos]
        return action


def file_problem(path: str | Path) -> str | None:
    """Why `path` cannot be a character file before it is read (missing, a directory), or None."""
    path = Path(path)
    return None if path.is_file() else "is a directory, not an MJCF file" if path.is_dir() else "no such file"


def _one_line(e: BaseException) -> str:
    """MuJoCo's message on one line (its parser's spans several), at most 200 characters."""
    text = " ".join(str(e).split())
    return text[:200] if text else type(e).__name__


def _check_skeleton(path: Path, model: mujoco.MjModel, fixed_root: bool) -> None:
    """CharacterError unless `model` has the bodies, joints (of the right types) and geoms the code needs."""
    kinds = {
        int(mujoco.mjtJoint.mjJNT_FREE): "free",
        int(mujoco.mjtJoint.mjJNT_BALL): "ball",
        int(mujoco.mjtJoint.mjJNT_SLIDE): "slide",
        int(mujoco.mjtJoint.mjJNT_HINGE): "hinge",
    }
    bodies = {model.body(i).name for i in range(model.nbody)}
    joints = {model.joint(j).name: kinds[int(model.jnt_type[j])] for j in range(model.njnt)}
    geoms = {model.geom(g).name for g in range(model.ngeom)}
    wanted = dict(SKELETON_JOINTS) if fixed_root else {"root": "free", **SKELETON_JOINTS}
    problems = []
    for kind, names, have in (
        ("body", SKELETON_BODIES, bodies),
        ("joint", wanted, joints),
        ("geom", SKELETON_GEOMS, geoms),
    ):
        missing = [n for n in names if n not in have]
        if missing:
            more = f" and {len(missing) - 4} more" if len(missing) > 5 else ""
            problems.append(f"no {kind} " + ", ".join(missing[: 4 if more else 5]) + more)
    problems += [f"joint {j} is {joints[j]}, not {k}" for j, k in wanted.items() if j in joints and joints[j] != k]
    problems += [f"joint {j} is {k} (only ball and hinge joints)" for j, k in joints.items() if k == "slide"]
    if problems:
        raise CharacterError(
            path, f"not the humanoid skeleton the code needs ({'; '.join(problems)}; see {HUMANOID_XML.name})"
        )


def _check_actuators(model: mujoco.MjModel, joint_names: list[str], joint_dof: list[slice], root_dofs: int) -> None:
    """One actuator per actuated dof, actuator i driving dof root_dofs + i, so that actions are in dof order."""
    if model.nu != model.nv - root_dofs:
        raise ValueError(f"{model.nu} actuators for {model.nv - root_dofs} actuated degrees of freedom (one each)")
    for i in range(model.nu):
        jid = model.actuator_trnid[i, 0]
        dofs = joint_dof[joint_names.index(model.joint(jid).name)]
        axis = int(np.argmax(np.abs(model.actuator_gear[i, :3])))
        expected = dofs.start + (axis if dofs.stop - dofs.start == 3 else 0)
        if expected != root_dofs + i:
            raise ValueError(f"actuator {model.actuator(i).name} drives dof {expected}, expected {root_dofs + i}")
