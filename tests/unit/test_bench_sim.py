"""The simulation benchmark runs and reports consistent figures (speed itself is not asserted)."""

import json

import numpy as np
import pytest
import torch

from orchestrator.bench.__main__ import main
from orchestrator.bench.sim import interleaved


def test_bench_sim_json(tmp_path, capsys):
    out = tmp_path / "sim.json"
    argv = ["sim", "--envs", "4", "--seconds", "0.3", "--block-seconds", "0.05", "--sim-hz", "480,240"]
    assert main([*argv, "--json", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads(out.read_text())
    assert printed == saved
    assert saved["envs"] == 4 and saved["threads"] == 1 and saved["pairs"] == 3
    assert [r["sim_hz"] for r in saved["rates"]] == [480, 240]
    for rate, k in zip(saved["rates"], (16, 8), strict=True):
        assert rate["substeps"] == k
        for key in ("random_policy", "mlp_policy"):
            r = rate[key]
            assert r["pairs"] == 3
            assert r["raw_physics_steps_per_s"] > 0 and r["control_steps_per_s"] > 0
            assert r["physics_steps_per_s"] == pytest.approx(r["control_steps_per_s"] * k)
            # The ratio is a median of pairwise ratios, inside its own quartiles.
            q1, q3 = r["ratio_quartiles"]
            assert 0 < q1 <= r["physics_step_ratio"] <= q3
            assert r["batched_physics_steps"] > 0 and r["batched_physics_steps"] % k == 0
            assert r["raw_physics_steps"] > 0 and r["raw_physics_steps"] % k == 0
            assert r["bad_qacc_warnings"] >= 0 and r["raw_bad_qacc_warnings"] >= 0
            assert r["episode_steps"] > 0 and r["raw_episode_steps"] > 0
        assert (
            rate["bad_qacc_warnings"]
            == rate["random_policy"]["bad_qacc_warnings"] + rate["mlp_policy"]["bad_qacc_warnings"]
        )


def test_bench_sim_table(capsys):
    assert main(["sim", "--envs", "2", "--seconds", "0.2", "--block-seconds", "0.05", "--sim-hz", "240"]) == 0
    out = capsys.readouterr().out
    assert "raw phys/s" in out and "MLP" in out and "ratio to raw" in out and "bad qacc" in out
    assert "3 pairs of 0.05 s blocks" in out


def test_bench_sim_refuses_bad_rates():
    with pytest.raises(SystemExit):
        main(["sim", "--sim-hz", "480,abc"])
    with pytest.raises(SystemExit):
        main(["sim", "--block-seconds", "0"])


class _Side:
    """A stand-in for either side of a pair: fixed rates, counts what it was asked."""

    def __init__(self, rates, k=4):
        self.rates, self.k = iter(rates), k
        self.actions = [np.zeros((1, 2))]
        self.calls = self.episodes = self.control_steps = 0
        self.bad_qacc_warnings = 0
        self.sim = self

    def warning_counts(self):
        return np.zeros(1, int)

    def block(self, seconds):
        self.calls += 1
        self.control_steps += 1
        self.episodes += 1
        return next(self.rates)


def test_interleaved_takes_the_median_of_pairwise_ratios():
    # Warm-up block first, then three pairs; raw rates 100, 200, 400 and batched control rates
    # 20, 50, 60 at K=4: pairwise ratios 0.8, 1.0, 0.6 (median 0.8), not median/median 0.9.
    raw = _Side([1.0, 100.0, 200.0, 400.0])
    batched = _Side([1.0, 20.0, 50.0, 60.0])
    r = interleaved(raw, batched, pairs=3, block_seconds=0.0)
    assert r["physics_step_ratio"] == pytest.approx(0.8)
    assert r["raw_physics_steps_per_s"] == 200.0 and r["control_steps_per_s"] == 50.0
    assert r["physics_steps_per_s"] == 200.0
    assert r["ratio_quartiles"] == pytest.approx([0.7, 0.9])


@pytest.mark.slow  # MuJoCo Warp's kernels (compiled once per machine, then cached)
def test_bench_sim_warp_json(tmp_path, capsys):
    pytest.importorskip("mujoco_warp")
    out = tmp_path / "warp.json"
    argv = ["sim", "--backend", "warp", "--device", "cpu", "--worlds", "2,4", "--cpu-envs", "4", "--seconds", "0.3"]
    assert main([*argv, "--block-seconds", "0.05", "--json", "--out", str(out)]) == 0
    saved = json.loads(out.read_text())
    assert json.loads(capsys.readouterr().out) == saved
    assert saved["device"] == "cpu" and saved["pairs"] == 3 and [r["worlds"] for r in saved["rows"]] == [2, 4]
    for row in saved["rows"]:
        assert row["substeps"] == 16
        for side in ("warp", "physics", "interface", "cpu"):
            assert row[f"{side}_control_steps_per_s"] > 0
            assert row[f"{side}_physics_steps_per_s"] == pytest.approx(16 * row[f"{side}_control_steps_per_s"])
        q1, q3 = row["ratio_quartiles"]
        assert 0 < q1 <= row["ratio_to_cpu"] <= q3
        assert row["overflowed_worlds"] == 0 and row["warp_resets_per_control_step"] >= 0


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_bench_sim_warp_refuses_a_gpu_that_is_not_there(capsys):
    pytest.importorskip("mujoco_warp")
    with pytest.raises(SystemExit) as e:
        main(["sim", "--backend", "warp", "--device", "cuda"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--device cuda" in err[0] and "no CUDA GPU" in err[0]


@pytest.mark.slow  # two short loops of the tracker, on each engine
def test_bench_pipeline_runs_a_method_on_each_simulator_engine(tmp_path, capsys):
    pytest.importorskip("mujoco_warp")
    out = tmp_path / "pipeline.json"
    argv = ["pipeline", "--algos", "tracker", "--runtimes", "local", "--workers", "1", "--iterations", "2"]
    # --sim-device names the warp engine's device only: MuJoCo C stays on the CPU (a GPU here or not).
    argv += ["--warmup", "1", "--envs", "4", "--sim", "mujoco,warp", "--sim-device", "cpu", "--out", str(out)]
    assert main(argv) == 0
    rows = json.loads(out.read_text())["results"]
    assert [r["sim"] for r in rows] == ["mujoco", "warp:cpu"]
    assert all(r["samples_per_s"] > 0 and r["updates_per_s"] > 0 for r in rows)
    assert "warp:cpu" in capsys.readouterr().out


def test_bench_pipeline_on_mujoco_c_ignores_the_warp_device(tmp_path):
    """`--sim-device` (cuda by default) is the warp engine's: a MuJoCo C pipeline runs on the CPU whatever it says."""
    out = tmp_path / "pipeline.json"
    argv = ["pipeline", "--algos", "tracker", "--runtimes", "local", "--workers", "1", "--iterations", "1"]
    argv += ["--warmup", "0", "--envs", "2", "--sim", "mujoco", "--sim-device", "cuda", "--out", str(out)]
    assert main(argv) == 0
    (row,) = json.loads(out.read_text())["results"]
    assert row["sim"] == "mujoco" and row["samples_per_s"] > 0
