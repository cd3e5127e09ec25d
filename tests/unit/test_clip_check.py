"""`python -m orchestrator.clips check`: summaries of good clips, one clear line for bad ones."""

import json
import subprocess
import sys

import numpy as np
import pytest

from orchestrator.clips import main


def _frame(n=44):
    f = [0.0333, 0.0, 0.85, 0.0, 1.0, 0.0, 0.0, 0.0]
    for width in (4, 4, 4, 1, 4, 4, 1, 4, 1, 4, 4, 1):
        f += [1.0, 0.0, 0.0, 0.0] if width == 4 else [0.0]
    return f[:n] + [0.0] * max(0, n - len(f))


def _write(tmp_path, frames, name="clip.txt", loop="none"):
    path = tmp_path / name
    path.write_text(json.dumps({"Loop": loop, "Frames": frames}))
    return path


def test_check_bundled_clip(capsys):
    assert main(["check", "humanoid3d_walk", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["frames"] == 39 and r["loop"]
    assert r["duration_s"] == pytest.approx(1.267, abs=0.01)
    assert r["rate_hz"] == pytest.approx(30.0, abs=0.1)
    assert -0.02 < r["lowest_foot_m"] < 0.0
    assert 1.0 < r["max_joint_speed_rad_s"] < 30.0


def test_check_prints_a_table(capsys):
    assert main(["check", "walker/turn_left0"]) == 0
    out = capsys.readouterr().out
    for word in ("frames", "duration", "rate", "lowest", "joint speed"):
        assert word in out


def _nan_frames():
    frames = [_frame() for _ in range(5)]
    frames[3][10] = float("nan")
    return frames


def _bad_quat_frames():
    frames = [_frame() for _ in range(5)]
    frames[2][8:12] = [0.1, 0.0, 0.0, 0.0]  # chest quaternion of norm 0.1
    return frames


CASES = [
    ("not JSON", lambda p: p.write_text("this is not json"), "not valid JSON"),
    ("nested too deeply", lambda p: p.write_text('{"Frames": ' + "[" * 100_000 + "]" * 100_000 + "}"), "nested"),
    ("no frames", lambda p: p.write_text(json.dumps({"Loop": "none", "Frames": []})), "no frames"),
    ("wrong width", lambda p: p.write_text(json.dumps({"Frames": [_frame(), _frame(43)]})), "frame 1: expected 44"),
    ("NaN", lambda p: p.write_text(json.dumps({"Frames": _nan_frames()}).replace("NaN", "NaN")), "frame 3: non-finite"),
    ("non-unit quaternion", lambda p: p.write_text(json.dumps({"Frames": _bad_quat_frames()})), "frame 2: non-unit"),
]


@pytest.mark.parametrize("case,write,message", CASES, ids=[c[0] for c in CASES])
def test_malformed_clip_gives_one_line_naming_file_and_frame(tmp_path, capsys, case, write, message):
    path = tmp_path / "bad_clip.txt"
    write(path)
    assert main(["check", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert str(path) in err and message in err


def test_missing_clip_is_named(capsys):
    assert main(["check", "humanoid3d_moonwalk"]) == 1
    assert "humanoid3d_moonwalk" in capsys.readouterr().err


def test_npz_clip_with_wrong_width(tmp_path, capsys):
    path = tmp_path / "short.npz"
    np.savez(path, qpos=np.zeros((4, 40)), fps=30.0)
    assert main(["check", str(path)]) == 1
    assert "expected 43 coordinates" in capsys.readouterr().err


def test_runs_as_a_module(tmp_path):
    bad = _write(tmp_path, [_frame(), _frame(12)])
    proc = subprocess.run(
        [sys.executable, "-m", "orchestrator.clips", "check", str(bad)], capture_output=True, text=True
    )
    assert proc.returncode == 1
    assert proc.stderr.strip().endswith("frame 1: expected 44 numbers, got 12")


def test_check_accepts_bvh(tmp_path, capsys, character):
    from workers.motion.formats import bvh, load_raw

    path = tmp_path / "walk.bvh"
    bvh.save(character, load_raw(character, "humanoid3d_walk"), path)
    assert main(["check", str(path), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["frames"] == 39 and r["rate_hz"] == pytest.approx(30.0, abs=0.1)
    assert -0.02 < r["lowest_foot_m"] < 0.0  # same poses as the JSON original
