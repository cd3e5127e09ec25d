"""Left-right reflection of the state features and of the actions, as index maps.

The reflection across the character's sagittal (x-z) plane, M = diag(1, −1, 1), with the left and right
bodies swapped: a polar vector v becomes M v (y negated), a pseudovector (an angular velocity, a rotation
vector) becomes −M v (x and z negated), and a rotation R becomes M R M, whose 6D columns are M R e_x and
−M R e_y. Every part of s (`workers.body.features.StateLayout`) and of an action (exponential-map PD targets
per ball joint, angles per hinge about y) is therefore a permutation with signs: `feature_mirror` and
`action_mirror` give them as (index [D], sign [D]) with mirrored = x[..., index] * sign, for NumPy arrays
and torch tensors alike. Mirroring twice is the identity. MuJoCo steps our symmetric character into the
exact reflection under reflected actions (tests/unit/test_mirror.py), so a controller mirrored this way
tracks a mirrored clip as the original tracks the clip: `workers.policies.ExpertPolicy` runs a clip's
expert on its mirror so.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from workers.body.character import Character
from workers.body.features import StateLayout

FLIP_Y = np.array([1.0, -1.0, 1.0])  # a polar vector under the reflection
FLIP_XZ = np.array([-1.0, 1.0, -1.0])  # a pseudovector (angular velocity, rotation vector)


@cache
def _feature_map(num_bodies: int, body_perm: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    layout = StateLayout(num_bodies)
    index = np.arange(layout.dim)
    sign = np.ones(layout.dim)
    perm = np.asarray(body_perm)

    def per_body(part: slice, width: int, signs: np.ndarray) -> None:
        cols = np.arange(part.start, part.stop).reshape(num_bodies, width)
        index[part] = cols[perm].ravel()
        sign[part] = np.tile(signs, num_bodies)

    per_body(layout.pos, 3, FLIP_Y)
    per_body(layout.rot, 6, np.concatenate((FLIP_Y, -FLIP_Y)))
    per_body(layout.lin_vel, 3, FLIP_Y)
    per_body(layout.ang_vel, 3, FLIP_XZ)
    per_body(layout.height, 1, np.ones(1))
    sign[layout.up] = FLIP_Y
    return index, sign


def feature_mirror(character: Character) -> tuple[np.ndarray, np.ndarray]:
    """(index [D], sign [D]): s of the reflected state is s[..., index] * sign."""
    return _feature_map(character.num_bodies, tuple(int(i) for i in character.body_mirror_perm()))


def action_mirror(character: Character) -> tuple[np.ndarray, np.ndarray]:
    """(index [A], sign [A]): the reflected action is action[..., index] * sign."""
    index, sign = np.zeros(character.num_actions, int), np.ones(character.num_actions)
    for j, src in enumerate(character.joint_mirror_perm()):
        dst, from_ = character.joint_dof[j], character.joint_dof[src]
        width = dst.stop - dst.start
        dst_act = np.arange(width) + dst.start - character.root_dofs
        index[dst_act] = np.arange(width) + from_.start - character.root_dofs
        if character.joint_types[j] == "ball":
            sign[dst_act] = FLIP_XZ
    return index, sign


def mirror_maps(character: Character) -> dict[str, np.ndarray]:
    """Both maps as plain arrays (what a mirrored expert's weights carry to a rollout worker)."""
    feature_index, feature_sign = feature_mirror(character)
    action_index, action_sign = action_mirror(character)
    return {
        "feature_index": feature_index,
        "feature_sign": feature_sign,
        "action_index": action_index,
        "action_sign": action_sign,
    }
