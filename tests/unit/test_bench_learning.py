"""`bench learning`: the first evaluation that reached each level, and the command's output."""

from __future__ import annotations

import json

from orchestrator.bench import learning
from orchestrator.bench.__main__ import main


def test_thresholds_are_the_first_point_at_each_level():
    curve = [
        {"seconds": 0.0, "samples": 0, "tracking_error": 0.30, "time_until_fall": 1.0},
        {"seconds": 60.0, "samples": 1000, "tracking_error": 0.14, "time_until_fall": 6.0},
        {"seconds": 120.0, "samples": 2000, "tracking_error": 0.16, "time_until_fall": 4.0},  # worse again
        {"seconds": 180.0, "samples": 3000, "tracking_error": 0.09, "time_until_fall": 7.0},
    ]
    got = {(t["metric"], t["level"]): (t["seconds"], t["samples"]) for t in learning.thresholds(curve)}
    assert got == {
        ("tracking_error", 0.15): (60.0, 1000),
        ("tracking_error", 0.10): (180.0, 3000),
        ("time_until_fall", 5.0): (60.0, 1000),
        ("time_until_fall", 20.0): (None, None),  # not reached
    }


def test_the_command_prints_one_json_object_with_the_thresholds_and_the_curve(tmp_path, capsys):
    figure = tmp_path / "learning.png"
    argv = ["learning", "--minutes", "0.05", "--eval-every", "2", "--fall-rollouts", "2", "--figure", str(figure)]
    assert main([*argv, "--json", "scale=smoke", "motion=walk", "eval.fall_max_seconds=2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [(t["metric"], t["level"]) for t in out["thresholds"]] == [
        ("tracking_error", 0.15), ("tracking_error", 0.10), ("time_until_fall", 5.0), ("time_until_fall", 20.0)
    ]  # fmt: skip
    assert set(out["thresholds"][0]) == {"metric", "level", "seconds", "samples"}
    seconds = [p["seconds"] for p in out["curve"]]
    assert seconds[0] == 0.0 and seconds == sorted(seconds) and seconds[-1] >= 3.0  # 0.05 min of training
    assert out["curve"][-1]["samples"] > 0 and figure.stat().st_size > 0
