"""`bench offline`: every lever timed on both offline learners, the table and JSON saying so (speed itself is the
benchmark's to measure, never asserted here)."""

from __future__ import annotations

import json

from orchestrator.bench import offline
from orchestrator.bench.__main__ import main


def test_bench_offline_times_every_lever_of_both_learners(capsys):
    result = offline.run("smoke", rounds=1, updates=1)
    assert [r["learner"] for r in result["rows"]] == ["vae", "world_model"]
    for row in result["rows"]:
        assert set(row["speedup"]) == set(offline.LEVERS) and all(v > 0 for v in row["speedup"].values())
        assert all(v > 0 for v in row["ms"].values())
    table = offline.format_table(result)
    header, rule, vae = table.splitlines()[1:4]
    assert header.count("|") == rule.count("|") == vae.count("|") == 11
    assert main(["offline", "--scale", "smoke", "--rounds", "1", "--updates", "1", "--learners", "vae", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert [r["learner"] for r in printed["rows"]] == ["vae"]
