"""Clip tools for users: `python -m orchestrator.clips check NAME_OR_PATH [--json]`.

`check` loads a clip in any supported format (a bundled DeepMimic name such as
`humanoid3d_walk` or `walker/turn_left0`, or a .txt/.json, .bvh or .npz path),
validates it as a run does (`workers.motion.clip.validate_raw`: frame width, NaN,
quaternions, times, and plausibility: the root within 1 km of the origin and 100 m
of its start, no root faster than 30 m/s, no joint faster than 50 rad/s), and prints
its frames, duration, rate, the lowest foot point over the clip and the largest
joint speed. A malformed or implausible clip, or a directory, exits with status 1
and one line naming the file and the frame.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from workers.body.character import Character
from workers.motion.clip import process
from workers.motion.errors import ClipError
from workers.motion.formats import bundled_clip_names, load_raw


def check(name_or_path: str, joint_map: dict[str, str] | None = None) -> dict:
    """Validate one clip and summarise it; raises ClipError on bad data."""
    character = Character.load()
    raw = load_raw(character, name_or_path, joint_map=joint_map)
    n = raw.qpos.shape[0]
    if n < 2:
        raise ClipError(raw.source or name_or_path, "a clip needs at least two frames", 0 if n else None)
    rate = (n - 1) / raw.duration
    # Processed at its own rate, the clip keeps (about) its source frames.
    clip = process(character, raw, rate)
    speeds = np.abs(clip.qvel[:, character.root_dofs :])
    frame, dof = np.unravel_index(int(np.argmax(speeds)), speeds.shape)
    dof_joint = _dof_joint_names(character)[dof]
    low = int(np.argmin(clip.foot_min_z))
    return {
        "clip": raw.name,
        "source": raw.source,
        "frames": n,
        "duration_s": raw.duration,
        "rate_hz": rate,
        "loop": raw.loop,
        "lowest_foot_m": float(clip.foot_min_z[low]),
        "lowest_foot_frame": low,
        "median_foot_m": float(np.median(clip.foot_min_z)),
        "max_joint_speed_rad_s": float(speeds[frame, dof]),
        "max_joint_speed_joint": dof_joint,
        "max_joint_speed_frame": int(frame),
    }


def _dof_joint_names(character: Character) -> list[str]:
    names = []
    for name, kind in zip(character.joint_names, character.joint_types, strict=True):
        names += [f"{name}_{a}" for a in "xyz"] if kind == "ball" else [name]
    return names


def format_report(r: dict) -> str:
    return "\n".join(
        [
            f"clip      {r['clip']}  ({r['source']})",
            f"frames    {r['frames']}  ({'cyclic' if r['loop'] else 'one-shot'})",
            f"duration  {r['duration_s']:.3f} s",
            f"rate      {r['rate_hz']:.2f} Hz",
            f"feet      lowest {r['lowest_foot_m'] * 100:+.1f} cm (frame {r['lowest_foot_frame']}), "
            f"median {r['median_foot_m'] * 100:+.1f} cm",
            f"speed     largest joint speed {r['max_joint_speed_rad_s']:.2f} rad/s "
            f"({r['max_joint_speed_joint']}, frame {r['max_joint_speed_frame']})",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestrator.clips", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_check = sub.add_parser("check", help="validate a clip and print its summary")
    p_check.add_argument("clip", help="bundled clip name or path (.txt/.json, .bvh, .npz)")
    p_check.add_argument("--json", action="store_true", help="print JSON")
    p_check.add_argument("--joint-map", help='BVH: {"source joint": "our body", ...} as JSON or a JSON file')
    sub.add_parser("list", help="list the bundled clips")
    args = parser.parse_args(argv)

    if args.command == "list":
        print("\n".join(bundled_clip_names()))
        return 0
    try:
        report = check(args.clip, _joint_map(parser, args.joint_map))
    except ClipError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    return 0


def _joint_map(parser: argparse.ArgumentParser, text: str | None) -> dict[str, str] | None:
    """--joint-map's JSON object, given inline or as a file."""
    if not text:
        return None
    try:
        value = json.loads(Path(text).read_text() if Path(text).is_file() else text)
    except (OSError, ValueError) as e:
        parser.error(f"--joint-map: neither a JSON object nor a JSON file ({e})")
    except RecursionError:
        parser.error("--joint-map: JSON nested deeper than Python's recursion limit")
    if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
        parser.error('--joint-map: expected a JSON object {"source joint": "our body", ...}')
    return value


if __name__ == "__main__":
    sys.exit(main())
