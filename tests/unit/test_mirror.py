"""Left-right symmetry: mirrored clips, state features, physics and the tracking evaluation.

Everything between a controller and its score is exactly mirror-equivariant: a
mirrored clip's reference is the reflected original over any number of cycles,
s of a reflected state is the reflected s, and the simulator driven by reflected
actions from a reflected state stays the reflection of the original, to the bit.
So `tracking_error` of a clip's mirror equals that of the original tracked by the
reflected controller M∘π∘M, and a gap between a clip and its mirror measures only
how far the learned controller is from being symmetric.

Why a trained controller can favour every mirror at once: the protocol tracks
each clip from its frame 0, and all six locomotion clips start in the same phase,
the right foot planted in front and the left foot behind, so the six pairs
compare one start with its reflection six times over rather than six independent
coin flips (`test_every_locomotion_clip_starts_with_the_right_foot_ahead`).

The reflection is across the sagittal x-z plane (y -> -y) with left and right
swapped: positions and linear velocities (x, -y, z), angular velocities (-x, y,
-z) (a pseudovector), rotations M R M with M = diag(1, -1, 1), ball-joint rotation
vectors (-x, y, -z), hinge angles about y unchanged.
"""

import numpy as np
import pytest
import torch

from workers.body import rotations as rot
from workers.body.features import state_features
from workers.body.mirror import FLIP_XZ, FLIP_Y, action_mirror, feature_mirror
from workers.evaluation.controller import tracking_error
from workers.models import body_state
from workers.motion.clip import mirror_qpos
from workers.motion.library import MotionLibrary
from workers.sim.env import BatchedSim, SimConfig
from workers.types import KinState

# conf/motion/locomotion.yaml's clips.
LOCOMOTION = ["humanoid3d_walk", "humanoid3d_run", "walker/turn_left0", "walker/turn_left1"]
LOCOMOTION += ["walker/turn_right0", "walker/turn_right1"]


@pytest.fixture(scope="module")
def locomotion(character, clip_cache) -> MotionLibrary:
    """Each clip followed by its mirror, as the default run loads them."""
    return MotionLibrary.load(character, LOCOMOTION, fps=30, mirror=True, cache_dir=clip_cache)


def mirror_kin(character, s: KinState) -> KinState:
    """The reflected state, computed from the original's numbers alone."""
    perm = character.body_mirror_perm()
    return KinState(
        qpos=mirror_qpos(character, s.qpos),
        qvel=s.qvel,  # not compared: MuJoCo's free-joint velocity has no simple per-slot map
        xpos=s.xpos[:, perm] * FLIP_Y,
        xquat=s.xquat[:, perm] * np.array([1.0, -1.0, 1.0, -1.0]),
        lin_vel=s.lin_vel[:, perm] * FLIP_Y,
        ang_vel=s.ang_vel[:, perm] * FLIP_XZ,
    )


def mirror_features(character, s: np.ndarray) -> np.ndarray:
    """s [N, D] of the reflected state, from s of the original (`workers.body.mirror.feature_mirror`)."""
    index, sign = feature_mirror(character)
    return s[..., index] * sign


# ----------------------------------------------------------------------------
# The data and the features
# ----------------------------------------------------------------------------
def test_mirrored_clips_are_reflections_over_three_cycles(character, locomotion):
    """The reflection must hold past the clip's end too: cycle_yaw changes sign, cycle_shift's y."""
    for orig in range(0, locomotion.num_clips, 2):
        frames = np.arange(3 * locomotion.num_frames[orig] + 1)
        expected = mirror_kin(character, locomotion.state(np.full(len(frames), orig), frames))
        got = locomotion.state(np.full(len(frames), orig + 1), frames)
        for field in ("xpos", "lin_vel", "ang_vel"):
            np.testing.assert_allclose(getattr(got, field), getattr(expected, field), atol=1e-9, err_msg=field)
        np.testing.assert_allclose(rot.angle(rot.mul(rot.conj(got.xquat), expected.xquat)), 0.0, atol=1e-6)
        np.testing.assert_allclose(got.qpos[:, :3], expected.qpos[:, :3], atol=1e-9)
        assert locomotion.cycle_yaw[orig + 1] == pytest.approx(-locomotion.cycle_yaw[orig], abs=1e-12)


def test_state_features_are_mirror_equivariant(character, locomotion):
    """s of a mirrored frame is the reflected s of the original, in NumPy and in torch."""
    n = locomotion.total_frames
    clips = np.searchsorted(locomotion.offsets, np.arange(n), side="right") - 1
    frames = np.arange(n) - locomotion.offsets[clips]
    orig = clips - clips % 2
    s_orig, s_mirr = locomotion.state(orig, frames), locomotion.state(orig + 1, frames)
    np.testing.assert_allclose(state_features(s_mirr), mirror_features(character, state_features(s_orig)), atol=1e-6)
    torch_mirr = body_state.features(torch.from_numpy(body_state.pack(s_mirr))).numpy()
    torch_orig = body_state.features(torch.from_numpy(body_state.pack(s_orig))).numpy()
    np.testing.assert_allclose(torch_mirr, mirror_features(character, torch_orig), atol=1e-6)


def test_every_locomotion_clip_starts_with_the_right_foot_ahead(character, locomotion):
    """Frame 0 of each original: the right foot on the ground 12-32 cm ahead of the root (walk +0.24 m,
    run +0.12 m, turns +0.29 to +0.32 m), the left foot 26-51 cm behind it (walk -0.35 m, run -0.51 m).
    Tracking from frame 0 therefore starts all six originals in one phase and all six mirrors in its
    reflection, so their errors are six looks at the same comparison, not six independent ones."""
    right, left = (character.body_names.index(n) for n in ("right_ankle", "left_ankle"))
    for orig in range(0, locomotion.num_clips, 2):
        s = locomotion.state(np.array([orig]), np.array([0]))
        heading = rot.yaw_matrix(-rot.yaw(s.xquat[0, 0]))
        ahead = (s.xpos[0] - s.xpos[0, 0]) @ heading.T
        name = locomotion.names[orig]
        assert ahead[right, 0] > 0.1 and ahead[left, 0] < -0.25, name
        assert s.xpos[0, right, 2] < 0.1, name


# ----------------------------------------------------------------------------
# The physics and the evaluation
# ----------------------------------------------------------------------------
def test_simulation_stays_the_reflection_under_reflected_actions(character, locomotion):
    """Walk and its mirror from frame 0, driven by the reference's next pose plus noise and its reflection:
    the mirror environment stays the reflection of the other (MuJoCo is symmetric here to the bit)."""
    walk = locomotion.clip_id("humanoid3d_walk")
    sim = BatchedSim(character, locomotion, 2, SimConfig(tracking_error_m=0.0))
    sim.reset(np.arange(2), np.array([walk, walk + 1]), np.zeros(2, int))
    perm, sign = action_mirror(character)
    rng = np.random.default_rng(0)
    for _ in range(15):
        ref = locomotion.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        actions = character.qpos_to_action(ref.qpos)
        noise = rng.normal(scale=0.2, size=character.num_actions)
        actions[0] += noise
        actions[1] += noise[perm] * sign
        result = sim.step(actions)
        expected = mirror_kin(character, result.kin[:1])
        np.testing.assert_allclose(result.kin.xpos[1:], expected.xpos, atol=1e-9)
        np.testing.assert_allclose(result.kin.ang_vel[1:], expected.ang_vel, atol=1e-7)


def test_a_mirrored_clip_scores_what_the_reflected_controller_scores_on_the_original(character, locomotion):
    """An asymmetric policy (a constant offset on the right hip) makes walk and its mirror differ; the
    reflected policy swaps the two numbers. A gap between a clip and its mirror is the controller's."""
    lib = MotionLibrary(character, locomotion.clips[:2])  # walk, walk_mirror
    perm, sign = action_mirror(character)
    offset = np.zeros(character.num_actions)
    offset[character.joint_dof[character.joint_names.index("right_hip")].start - character.root_dofs] = 0.3

    def lopsided(sim):
        target = lib.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        return character.qpos_to_action(target.qpos) + offset

    def reflected(sim):
        # M∘π∘M: the reference-target part is itself symmetric, so only the offset is reflected.
        target = lib.state(sim.clip_id, sim.start_frame + sim.steps + 1)
        return character.qpos_to_action(target.qpos) + offset[perm] * sign

    plain = tracking_error(None, character, lib, clip_seconds=0.5, policy=lopsided)
    mirrored = tracking_error(None, character, lib, clip_seconds=0.5, policy=reflected)
    assert abs(plain["humanoid3d_walk"] - plain["humanoid3d_walk_mirror"]) > 1e-3
    assert mirrored["humanoid3d_walk"] == pytest.approx(plain["humanoid3d_walk_mirror"], abs=1e-9)
    assert mirrored["humanoid3d_walk_mirror"] == pytest.approx(plain["humanoid3d_walk"], abs=1e-9)
