"""scripts/learning_seeds.py's statistics on rows whose answers are worked by hand (the runs themselves are the
learning test's, which has its own)."""

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "learning_seeds.py"
spec = importlib.util.spec_from_file_location("learning_seeds", SCRIPT)
learning_seeds = importlib.util.module_from_spec(spec)
spec.loader.exec_module(learning_seeds)


def rows(first: list[float], second: list[float]) -> list[dict]:
    out = []
    for seed, (a, b) in enumerate(zip(first, second, strict=True)):
        out += [
            {"seed": seed, "mode": "eager", "test": a, "starts": a},
            {"seed": seed, "mode": "default", "test": b, "starts": b},
        ]
    return out


def test_paired_interval_and_margin_by_hand():
    # differences 0.01, 0.02, 0.03: mean 0.02, sd 0.01, sem 0.01/sqrt(3) = 0.005774
    r = rows([0.30, 0.30, 0.30], [0.31, 0.32, 0.33])
    pairs, d = learning_seeds.differences(r, "eager", "default", "test")
    assert d == pytest.approx([0.01, 0.02, 0.03])
    line = learning_seeds.summary(r, "eager", "default", margin=0.10)[0]
    assert "+0.020, 95% t interval [-0.005, +0.045]" in line  # t(2, 0.975) = 4.303: +-0.0248
    # two metrics, Bonferroni: 97.5% each, t(2, 0.9875) = 6.205: +-0.0358
    assert line.endswith("97.5% [-0.016, +0.056]: no worse")  # ends below 0.10
    assert learning_seeds.summary(r, "eager", "default", margin=0.03)[0].endswith("not resolved")  # straddles 0.03
    worse = learning_seeds.summary(r, "eager", "default", margin=-0.05)[0]
    assert worse.endswith("worse by more than the margin")  # starts above -0.05


def test_seed_ranges():
    assert learning_seeds.seeds("6-9") == [6, 7, 8, 9]
    assert learning_seeds.seeds("0,2,5") == [0, 2, 5]
    assert learning_seeds.seeds("") == []


def test_rows_are_written_as_each_run_ends(tmp_path, monkeypatch):
    """A run that fails after others leaves the finished runs' rows in --json."""
    done = []

    def one(seed, mode, starts, iterations):
        if (seed, mode) == (1, "default"):
            raise SystemExit("learning_seeds: seed 1, default failed")
        done.append((seed, mode))
        return {"seed": seed, "mode": mode, "test": 0.3, "starts": 0.3}

    out = tmp_path / "rows.json"
    monkeypatch.setattr(learning_seeds, "one", one)
    monkeypatch.setattr("sys.argv", ["learning_seeds.py", "--seeds", "0-1", "--json", str(out)])
    with pytest.raises(SystemExit):
        learning_seeds.main()
    written = json.loads(out.read_text())
    assert [(r["seed"], r["mode"]) for r in written] == done == [(0, "eager"), (0, "default"), (1, "eager")]
