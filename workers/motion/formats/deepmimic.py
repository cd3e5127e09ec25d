"""DeepMimic's JSON clips (the ones bundled in the `pybullet` package).

Each frame has 44 numbers: frame duration; root position (3); root rotation
(w, x, y, z); then chest, neck, right hip (4), right knee (1), right ankle,
right shoulder (4), right elbow (1), left hip (4), left knee (1), left ankle,
left shoulder (4), left elbow (1). Rotations are local quaternions, knees and
elbows hinge angles in radians, the world y-up (x forward, z to the right).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from workers.body.character import Character
from workers.motion.clip import RawClip
from workers.motion.errors import ClipError

FRAME_WIDTH = 44
# (joint name, width) after the duration, root position and root rotation.
JOINT_LAYOUT = [
    ("chest", 4), ("neck", 4),
    ("right_hip", 4), ("right_knee", 1), ("right_ankle", 4), ("right_shoulder", 4), ("right_elbow", 1),
    ("left_hip", 4), ("left_knee", 1), ("left_ankle", 4), ("left_shoulder", 4), ("left_elbow", 1),
]  # fmt: skip

# y-up (x fwd, y up, z right) -> z-up (x fwd, y left, z up): (x, y, z) -> (x, -z, y).
Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def y_up_to_z_up_vec(v: np.ndarray) -> np.ndarray:
    return v @ Y_TO_Z.T


def y_up_to_z_up_quat(q: np.ndarray) -> np.ndarray:
    """Conjugating a rotation by the change of axes rotates its vector part."""
    return np.concatenate((q[..., :1], y_up_to_z_up_vec(q[..., 1:])), axis=-1)


def z_up_to_y_up_vec(v: np.ndarray) -> np.ndarray:
    return v @ Y_TO_Z


def z_up_to_y_up_quat(q: np.ndarray) -> np.ndarray:
    return np.concatenate((q[..., :1], z_up_to_y_up_vec(q[..., 1:])), axis=-1)


def read_frames(path: Path) -> tuple[np.ndarray, bool]:
    """The [T, 44] frame array and the loop flag, or a ClipError naming the file and frame."""
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as e:
        raise ClipError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    except RecursionError:  # Python's parser recurses per level of nesting
        raise ClipError(path, "not valid JSON for a clip (nested deeper than Python's recursion limit)") from None
    except UnicodeDecodeError:
        raise ClipError(path, "not valid JSON (not text)") from None
    except OSError as e:
        raise ClipError(path, f"cannot be read ({e.strerror or type(e).__name__})") from None
    if not isinstance(doc, dict) or "Frames" not in doc:
        raise ClipError(path, 'no "Frames" list (not a DeepMimic clip)')
    frames = doc["Frames"]
    if not isinstance(frames, list) or len(frames) == 0:
        raise ClipError(path, "no frames")
    for i, frame in enumerate(frames):
        if not isinstance(frame, list) or len(frame) != FRAME_WIDTH:
            width = len(frame) if isinstance(frame, list) else type(frame).__name__
            raise ClipError(path, f"expected {FRAME_WIDTH} numbers, got {width}", i)
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in frame):
            raise ClipError(path, "a value is not a number", i)
    arr = np.asarray(frames, dtype=float)
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise ClipError(path, "non-finite value (NaN or inf)", int(np.argmax(bad)))
    loop = str(doc.get("Loop", "none")).lower() == "wrap"
    return arr, loop


def load(character: Character, path: str | Path, name: str | None = None) -> RawClip:
    path = Path(path)
    frames, loop = read_frames(path)
    n = frames.shape[0]
    qpos = np.zeros((n, character.model.nq))
    qpos[:, :3] = y_up_to_z_up_vec(frames[:, 1:4])
    qpos[:, 3:7] = y_up_to_z_up_quat(frames[:, 4:8])
    col = 8
    for joint, width in JOINT_LAYOUT:
        sl = character.joint_qpos[character.joint_names.index(joint)]
        vals = frames[:, col : col + width]
        qpos[:, sl] = y_up_to_z_up_quat(vals) if width == 4 else vals
        col += width
    # A frame's duration is the time to the next frame; the last one's is unused.
    durations = frames[:-1, 0]
    bad = np.flatnonzero(durations <= 0)
    if bad.size:
        raise ClipError(path, f"frame duration must be positive, got {durations[bad[0]]}", int(bad[0]))
    times = np.concatenate(([0.0], np.cumsum(durations)))
    return RawClip(name=name or path.stem, qpos=qpos, times=times, loop=loop, source=str(path))


def save(character: Character, raw: RawClip, path: str | Path) -> None:
    """Write a clip back in DeepMimic's format (y-up)."""
    n = raw.qpos.shape[0]
    frames = np.zeros((n, FRAME_WIDTH))
    dur = np.diff(raw.times)
    frames[:, 0] = np.concatenate((dur, dur[-1:] if n > 1 else [1 / 30]))
    frames[:, 1:4] = z_up_to_y_up_vec(raw.qpos[:, :3])
    frames[:, 4:8] = z_up_to_y_up_quat(raw.qpos[:, 3:7])
    col = 8
    for joint, width in JOINT_LAYOUT:
        vals = raw.qpos[:, character.joint_qpos[character.joint_names.index(joint)]]
        frames[:, col : col + width] = z_up_to_y_up_quat(vals) if width == 4 else vals
        col += width
    doc = {"Loop": "wrap" if raw.loop else "none", "Frames": frames.tolist()}
    Path(path).write_text(json.dumps(doc))
