"""The task stage at smoke size: a ControlVAE skill stage, then heading on its frozen decoder, in one store."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import stage_runs
import torch
from stage_runs import runs_of

from orchestrator import stages
from orchestrator.build import run, train_stage
from orchestrator.components.task import skill_model
from orchestrator.schema import Config
from orchestrator.upstream import StageError

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow  # a skill stage and three task runs: ~90 s


def smoke_config(run_dir: Path, *overrides: str) -> Config:
    return stage_runs.smoke_config(run_dir, "algo=task", *overrides)


@pytest.fixture(scope="module")
def task_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("task")
    uri = f"sqlite:///{root / 'store.db'}"
    cfg = smoke_config(root / "task", f"tracking.uri={uri}")
    run(cfg)
    return {"root": root, "uri": uri, "cfg": cfg}


def test_a_task_run_trains_on_a_frozen_skill_stage_and_reports_the_papers_measures(task_run):
    uri = task_run["uri"]
    (skill,) = runs_of(uri, "controlvae")
    (task,) = runs_of(uri, "task")
    assert task.info.status == "FINISHED"
    assert task.data.tags["upstream.skill"] == skill.info.run_id
    m = task.data.metrics
    for key in ("eval/task_return", "eval/task_success", "eval/style_deviation_deg", "eval/time_until_fall_mean"):
        assert key in m
    assert m["eval/style_deviation_deg"] == 0.0  # σ = 0: the decoder's own actions
    assert 0.0 <= m["eval/task_return"] <= 1.0 and m["task/updates"] > 0
    # The skill stage's own evaluation, beside the task's.
    assert m["skill/tracking_error_mean"] == skill.data.metrics["eval/tracking_error_mean"]
    assert m["skill/random_sampling_fell"] == skill.data.metrics["eval/random_sampling_fell"]


def test_the_decoder_the_task_used_is_the_skill_stages_last_checkpoint(task_run):
    """The task run's checkpoint holds only the task policy; the skill it read is bit-identical to the stage's."""
    uri, root = task_run["uri"], task_run["root"]
    (skill,) = runs_of(uri, "controlvae")
    up = stages.ensure(
        "skill", f"run:{skill.info.run_id}", task_run["cfg"], uri, root / "again", "default", train_stage
    )
    payload = skill_model(up, world_model=True)
    stage_state = up.checkpoint()["vae"]["learner"]["module"]
    assert all(torch.equal(payload["module"][k], stage_state[k]) for k in stage_state)
    task_ckpt = sorted((root / "task" / "checkpoints").glob("ckpt-*.pt"))[-1]
    state = torch.load(task_ckpt, weights_only=True)
    assert not any(k.startswith(("policy.", "prior.", "posterior.")) for k in state["task"]["learner"]["module"])


def test_a_task_refuses_an_upstream_run_that_is_not_a_skill_model(task_run):
    uri, root = task_run["uri"], task_run["root"]
    (task,) = runs_of(uri, "task")
    cfg = smoke_config(root / "bad", f"tracking.uri={uri}", f"algo.needs.skill=run:{task.info.run_id}")
    with pytest.raises(StageError, match=f"run {task.info.run_id}.*a task run is not a skill model"):
        run(cfg)
    cli = subprocess.run(
        [
            sys.executable,
            "-m",
            "orchestrator",
            "algo=task",
            "runtime=local",
            "eval.video=false",
            "scale=smoke",
            "motion=walk",
            "progress=false",
            f"tracking.uri={uri}",
            f"algo.needs.skill=run:{task.info.run_id}",
            f"run_dir={root / 'bad-cli'}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cli.returncode != 0
    assert "is not a skill model" in cli.stderr.strip().splitlines()[-1]


def test_sigma_bounds_the_helper_in_a_run(task_run):
    """σ = 0.5 on point goal reuses the skill stage; the measured deviation stays within σ (in degrees)."""
    uri, root = task_run["uri"], task_run["root"]
    cfg = smoke_config(root / "sigma", f"tracking.uri={uri}", "algo.task.task=point_goal", "algo.task.sigma=0.5")
    run(cfg)
    assert len(runs_of(uri, "controlvae")) == 1  # the skill stage was reused
    sigma_run = [r for r in runs_of(uri, "task") if r.data.params.get("algo.task.sigma") == "0.5"]
    m = sigma_run[0].data.metrics
    assert 0 < m["eval/style_deviation_deg"] <= math.degrees(0.5)
    assert 0 < m["rollout/helper_deviation_deg"] <= math.degrees(0.5)
