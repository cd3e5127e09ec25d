"""The learner benchmark runs and reports consistent figures (speed itself is not asserted)."""

from __future__ import annotations

import json
from dataclasses import fields

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from orchestrator.bench import learners as bench
from orchestrator.bench import matmuls
from orchestrator.bench.__main__ import main
from orchestrator.compose import compose, validate


def test_bench_learners_json(tmp_path, capsys):
    out = tmp_path / "learners.json"
    argv = ["learners", "--learners", "world_model,ppo", "--sizes", "small", "--seconds", "0.05", "--threads", "1"]
    assert main([*argv, "--json", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads(out.read_text())
    assert printed == saved
    assert saved["benchmark"] == "learners" and saved["threads"] == 1
    assert [(r["learner"], r["size"]) for r in saved["results"]] == [("world_model", "small"), ("ppo", "small")]
    for r in saved["results"]:
        assert r["repeats"] >= bench.MIN_REPEATS
        assert r["flops_per_update"] > 0 and r["distinct_matmuls"] > 0
        assert r["updates_per_s"] == pytest.approx(1 / r["update_s_median"])
        assert r["achieved_gflops_per_s"] == pytest.approx(r["gflop_per_update"] * r["updates_per_s"])
        assert r["share_of_peak"] == pytest.approx(r["achieved_gflops_per_s"] / r["matmul_peak_gflops_per_s"])
        assert 0 < r["share_of_peak"] <= 1.5
        assert sum(m["gflop"] for m in r["top_matmuls"]) <= r["gflop_per_update"] * (1 + 1e-9)
    table = bench.format_table(saved)
    assert "world_model" in table and "ppo" in table and "share" in table


@pytest.mark.parametrize("name", ["world_model", "ppo"])
def test_recorded_flops_match_flop_counter(name):
    """The recorder counts the same FLOPs as torch's FlopCounterMode, backward pass included."""
    case = bench.BUILDERS[name]("small", torch.Generator().manual_seed(0))
    with FlopCounterMode(display=False) as counter:
        case.learner.update(case.batch)
    recorder = matmuls.MatmulRecorder()
    with recorder:
        case.learner.update(case.batch)
    assert recorder.flops == counter.get_total_flops() > 0


def test_parse_names():
    assert bench.parse_names(None, bench.LEARNERS, "learner") == list(bench.LEARNERS)
    assert bench.parse_names("disc, vae,disc", bench.LEARNERS, "learner") == ["discriminator", "vae"]
    with pytest.raises(ValueError, match="unknown size"):
        bench.parse_names("huge", bench.SIZES, "size")


@pytest.mark.slow  # compiles PPO's loss (seconds)
def test_compiled_rows_time_an_eager_twin_in_the_same_rounds():
    r = bench.run(["ppo", "discriminator"], ["small"], seconds=0.2, threads=1, compile_mode="default")
    ppo, disc = r["results"]
    assert r["compile"] == "default" and ppo["compiled"] == "default" and ppo["compile_s"] > 0
    assert ppo["eager_updates_per_s"] > 0
    assert ppo["compiled_over_eager"] == pytest.approx(ppo["updates_per_s"] / ppo["eager_updates_per_s"])
    assert disc["compiled"] is None  # its gradient penalty stays eager
    assert "x eager" in bench.format_table(r).splitlines()[2]


def _fields(config) -> dict:
    """A config's fields, lists read as tuples (YAML gives lists where the dataclasses default to tuples)."""
    return {f.name: tuple(v) if isinstance(v := getattr(config, f.name), list) else v for f in fields(config)}


@pytest.mark.parametrize(
    ("algo", "section", "config"),
    [
        ("controlvae", "world_model", bench.world_model_config),
        ("controlvae", "vae", bench.vae_config),
        ("amp", "discriminator", bench.discriminator_config),
        ("amp", "ppo", bench.ppo_config),
        ("task", "task", bench.task_config),
    ],
)
def test_the_laptop_size_is_the_laptop_scale_of_its_method(algo, section, config):
    """`--sizes laptop` measures the learners the default run (and AMP's and the task's laptop runs) train:
    every field as the composed config has it, so that a change to conf/algo_scale/*_laptop.yaml fails here."""
    cfg = validate(compose(["run_dir=unused", f"algo={algo}"]))
    assert _fields(config("laptop")) == _fields(getattr(cfg.algo, section))
    assert _fields(config("laptop")) != _fields(config("small"))  # a size of its own


def test_the_laptop_vae_learns_through_the_laptop_world_model():
    case = bench.BUILDERS["vae"]("laptop", torch.Generator().manual_seed(0))
    hidden = [m.out_features for m in case.learner.world_model.modules() if isinstance(m, torch.nn.Linear)][:-1]
    assert tuple(hidden) == bench.world_model_config("laptop").hidden == (256, 256, 256)
    assert "MLP 2x256" in case.description
