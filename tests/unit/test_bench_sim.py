"""The simulation benchmark runs and reports consistent figures (speed itself is not asserted)."""

import json

from orchestrator.bench.__main__ import main


def test_bench_sim_json(tmp_path, capsys):
    out = tmp_path / "sim.json"
    assert main(["sim", "--envs", "4", "--seconds", "0.3", "--json", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads(out.read_text())
    assert printed == saved
    assert saved["substeps"] == 16 and saved["envs"] == 4
    for key in ("random_policy", "mlp_policy"):
        r = saved[key]
        assert r["control_steps_per_s"] > 0
        assert r["physics_steps_per_s"] == r["control_steps_per_s"] * 16
        assert abs(r["physics_step_ratio"] - r["physics_steps_per_s"] / saved["raw_physics_steps_per_s"]) < 1e-9


def test_bench_sim_table(capsys):
    assert main(["sim", "--envs", "2", "--seconds", "0.2"]) == 0
    out = capsys.readouterr().out
    assert "raw mj_step" in out and "MLP" in out and "ratio to raw" in out
