"""Stages with reuse, on the PhysicsVAE pipeline at smoke size: tracker -> demos -> simulation_layer -> physicsvae.

One pipeline is trained once for the module into its own MLflow store; the tests then ask it for stages
again (reused, or not), break its artifacts, and train PhysicsVAE on its data.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient
from stage_runs import runs_of, smoke_config

from orchestrator import stages
from orchestrator.build import run, train_stage
from orchestrator.components.physicsvae import PhysicsVAEActor, SimulationLayerActor
from orchestrator.tracking.query import find_finished
from orchestrator.upstream import load_demos

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    """A finished physicsvae run and its three upstream stages, in one store."""
    root = tmp_path_factory.mktemp("pipeline")
    uri = f"sqlite:///{root / 'store.db'}"
    cfg = smoke_config(root / "physicsvae", "algo=physicsvae", f"tracking.uri={uri}")
    run(cfg)
    return {"root": root, "uri": uri, "cfg": cfg}


def test_the_pipeline_ran_each_stage_once_and_linked_them(pipeline):
    uri = pipeline["uri"]
    counts = {a: len(runs_of(uri, a)) for a in ("tracker", "demos", "simulation_layer", "physicsvae")}
    assert counts == {"tracker": 1, "demos": 1, "simulation_layer": 1, "physicsvae": 1}
    pv = runs_of(uri, "physicsvae")[0]
    tags = pv.data.tags
    assert tags["upstream.demos"] == runs_of(uri, "demos")[0].info.run_id
    assert tags["upstream.world_model"] == runs_of(uri, "simulation_layer")[0].info.run_id
    assert tags["expert_run_id"] == runs_of(uri, "tracker")[0].info.run_id  # which expert it came from
    assert "expert/tracking_error_mean" in pv.data.metrics  # the expert's quality, reported downstream
    assert all(r.info.status == "FINISHED" for a in counts for r in runs_of(uri, a))


def test_an_identical_stage_is_reused_and_a_changed_alpha_is_not(pipeline):
    cfg, uri, root = pipeline["cfg"], pipeline["uri"], pipeline["root"]
    messages: list[str] = []
    same = stages.ensure("pv", "physicsvae", cfg, uri, root / "again", "default", train_stage, messages.append)
    assert same.reused and same.run_id == runs_of(uri, "physicsvae")[0].info.run_id
    assert "vae" in same.checkpoint()  # its artifacts are found and load
    assert len(runs_of(uri, "physicsvae")) == 1
    changed = stages.ensure(
        "pv", "physicsvae algo.vae.alpha=0.003", cfg, uri, root / "alpha", "default", train_stage, print
    )
    assert not changed.reused and changed.stage_hash != same.stage_hash
    assert len(runs_of(uri, "physicsvae")) == 2
    assert len(runs_of(uri, "tracker")) == 1 and len(runs_of(uri, "simulation_layer")) == 1  # upstream reused


def test_a_changed_upstream_stage_invalidates_the_ones_below(pipeline):
    cfg, uri = pipeline["cfg"], pipeline["uri"]
    before = runs_of(uri, "physicsvae")[0].data.tags["stage_hash"]
    algo = dataclasses.replace(
        cfg.algo, needs={**cfg.algo.needs, "world_model": "simulation_layer algo.world_model.lr=0.002"}
    )
    changed = dataclasses.replace(cfg, algo=algo, run_dir=str(pipeline["root"] / "new-layer"))
    run(changed)
    new = [r for r in runs_of(uri, "physicsvae") if r.data.tags["stage_hash"] != before]
    layer_runs = runs_of(uri, "simulation_layer")
    assert len(layer_runs) == 2  # the layer was retrained with its new setting ...
    assert any(r.data.tags["upstream.world_model"] not in {w.info.run_id for w in layer_runs[1:]} for r in new)
    tags = [r for r in new if r.data.tags["upstream.world_model.reused"] == "false"][0].data.tags
    assert tags["upstream.demos.reused"] == "true"  # ... the stages above it were not
    assert len(runs_of(uri, "tracker")) == 1 and len(runs_of(uri, "demos")) == 1


def cli(*overrides: str, timeout: int = 600) -> subprocess.CompletedProcess:
    command = [
        sys.executable,
        "-m",
        "orchestrator",
        "scale=smoke",
        "motion=walk",
        "runtime=local",
        "eval.video=false",
        "progress=false",
    ]
    command += overrides
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def artifact_dir(uri: str, run_id: str) -> Path:
    return Path(MlflowClient(uri).get_run(run_id).info.artifact_uri.removeprefix("file://"))


def test_a_changed_or_missing_upstream_artifact_is_named_and_the_stage_trained_again(pipeline, tmp_path):
    """A stage's file that no longer matches its manifest (or is gone) is one line naming the run and the file;
    that run is not used, and with no other verified run the stage is trained again."""
    uri = pipeline["uri"]
    demos_run = runs_of(uri, "demos")[0].info.run_id
    demos_file = artifact_dir(uri, demos_run) / "demos" / "demos.npz"
    saved = tmp_path / "demos.npz"
    shutil.copy(demos_file, saved)
    try:
        demos_file.write_bytes(b"not a zip file")
        proc = cli("algo=physicsvae", "algo.vae.alpha=0.0002", f"tracking.uri={uri}", f"run_dir={tmp_path / 'a'}")
        assert proc.returncode == 0, proc.stderr[-2000:]
        line = (
            f"stage demos (demos, run {demos_run}): artifact demos/demos.npz does not match its SHA-256 in "
            "artifacts.sha256.json (changed since the run); not used"
        )
        assert line in proc.stderr.splitlines(), proc.stderr[-2000:]
        assert "stage demos: no finished demos run with hash" in proc.stderr
        retrained = runs_of(uri, "demos")[0].info.run_id
        assert retrained != demos_run
        (artifact_dir(uri, retrained) / "demos" / "demos.npz").unlink()
        proc = cli("algo=physicsvae", "algo.vae.alpha=0.0002", f"tracking.uri={uri}", f"run_dir={tmp_path / 'b'}")
        assert proc.returncode == 0, proc.stderr[-2000:]
        missing = [x for x in proc.stderr.splitlines() if "artifact demos/demos.npz is missing" in x]
        assert missing and missing[0].startswith(f"stage demos (demos, run {retrained}): "), proc.stderr[-2000:]
        assert missing[0].endswith("; not used")
    finally:
        shutil.copy(saved, demos_file)


def test_physicsvae_alpha_pulls_the_simulated_next_states_toward_the_demos(pipeline):
    """Known direction on real expert data: with α > 0 the decoder's actions, through the frozen layer, land
    nearer the demos' next states on held-out rollouts than with α = 0 (plain behaviour cloning).

    It needs data: with the smoke expert's six rollouts (158 training transitions) α lowered the training
    windows' error and raised the held-out one (overfitting); with forty (about 1,000) it lowers both.
    The margin is small because most of the error is the layer's own, which no action removes: on a layer
    of 60 epochs at the default rate (5e-4) α = 1 lowered the held-out error by 1.1% (25.18 against 25.45),
    and α = 3 or 10 by no more; a worse layer (20 epochs at 0.01) left it more to correct (6%)."""
    cfg, uri, root = pipeline["cfg"], pipeline["uri"], pipeline["root"]
    spec = "demos algo.demos.rollouts_per_clip=40 algo.demos.seconds=4"
    demos, _ = load_demos(stages.ensure("demos", spec, cfg, uri, root / "d40", "default", train_stage, print))
    offline = dataclasses.replace(cfg.algo.offline, holdout_rollouts=8)
    wm_cfg = smoke_config(root / "unused", "algo=simulation_layer")
    wm_cfg = dataclasses.replace(wm_cfg, algo=dataclasses.replace(wm_cfg.algo, offline=offline))
    torch.manual_seed(0)
    layer = SimulationLayerActor(wm_cfg, demos, 15, 28)
    for _ in range(60):
        layer.train_epoch()
    results = {}
    for alpha in (0.0, 1.0):
        vae = dataclasses.replace(cfg.algo.vae, alpha=alpha, lr=1e-3)
        c = dataclasses.replace(cfg, algo=dataclasses.replace(cfg.algo, vae=vae, offline=offline))
        torch.manual_seed(0)
        actor = PhysicsVAEActor(c, demos, 15, 28, (wm_cfg.algo.world_model, layer.learner.model.state_dict()))
        for _ in range(10):
            actor.train_epoch()
        results[alpha] = actor.validate()
        actor.heldout_starts = actor.train_starts
        results[alpha, "train"] = actor.validate()
    assert results[1.0]["heldout_sim_error"] < results[0.0]["heldout_sim_error"], results
    assert results[1.0, "train"]["heldout_sim_error"] < results[0.0, "train"]["heldout_sim_error"], results
    # ... at the cost of cloning the expert's (noisy) actions less closely
    assert results[1.0]["heldout_action_error"] > results[0.0]["heldout_action_error"], results


def test_ablation_alpha_smoke_gives_a_parent_with_a_child_per_point_the_stages_and_the_figure(tmp_path):
    sweep_dir = tmp_path / "sweep"
    proc = cli("+experiment=ablation_alpha", f"hydra.sweep.dir={sweep_dir}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads((sweep_dir / "sweep.json").read_text())
    client = MlflowClient(info["store"])
    parent = client.get_run(info["parent_run_id"])
    children = client.search_runs(
        [parent.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    alphas = sorted(float(c.data.params["algo.vae.alpha"]) for c in children)
    assert alphas == [0.0, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2]
    store = info["store"]
    assert len(runs_of(store, "tracker")) == 1 and len(runs_of(store, "simulation_layer")) == 1
    expert = runs_of(store, "tracker")[0].info.run_id
    assert {c.data.tags["expert_run_id"] for c in children} == {expert}
    assert parent.data.tags["upstream.demos.expert.0"] == expert  # the parent links every stage it used (one per clip)
    assert parent.data.tags["upstream.world_model"] == runs_of(store, "simulation_layer")[0].info.run_id
    assert all(c.data.tags["upstream.world_model.reused"] == "true" for c in children)
    artifacts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"spread.png", "comparison.png", "comparison.md", "stages.json"} <= artifacts
    table = (sweep_dir / "comparison.md").read_text()
    assert "the best α lies in 3e-4 … 3e-3" in table and "Stages shared by every point" in table


@pytest.mark.slow
def test_a_parallel_sweep_trains_the_expert_once(tmp_path):
    sweep_dir = tmp_path / "sweep"
    parallel = ("algo.vae.alpha=0,0.001", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    proc = cli("+experiment=ablation_alpha", f"hydra.sweep.dir={sweep_dir}", *parallel)
    assert proc.returncode == 0, proc.stderr[-3000:]
    store = json.loads((sweep_dir / "sweep.json").read_text())["store"]
    assert len(runs_of(store, "tracker")) == 1 and len(runs_of(store, "demos")) == 1
    points = runs_of(store, "physicsvae")
    assert len(points) == 2 and len({p.data.tags["expert_run_id"] for p in points}) == 1
    # The server is gone; the store is whole without it: a later command reads the stages' artifacts from it.
    demos_run = runs_of(store, "demos")[0].info.run_id
    local = MlflowClient(store).download_artifacts(demos_run, "demos/manifest.json", str(tmp_path))
    assert json.loads(Path(local).read_text())["expert_run"] == runs_of(store, "tracker")[0].info.run_id


def test_pulse_distillation_lowers_the_action_error_on_the_students_own_states(pipeline):
    """The student acts, the expert labels its states (DAgger): the distillation error on those states falls,
    the run reuses the pipeline's expert, and evaluation reports PULSE's success rate and MPJPE."""
    uri, root = pipeline["uri"], pipeline["root"]
    cfg = smoke_config(root / "pulse", "algo=pulse", f"tracking.uri={uri}", "algo.loop.iterations=16")
    run(cfg)
    # PULSE's teacher observes s_g-mimic (conf/algo/pulse.yaml): a tracker stage of its own beside the
    # pipeline's, which observes the reference in its own frame.
    trackers = {r.data.params["algo.imitation.observation"]: r.info.run_id for r in runs_of(uri, "tracker")}
    assert set(trackers) == {"imitation", "mimic"}
    (pulse,) = runs_of(uri, "pulse")
    assert pulse.data.tags["expert_run_id"] == trackers["mimic"]
    assert pulse.data.params["algo.vae.goal"] == "mimic"
    history = sorted(MlflowClient(uri).get_metric_history(pulse.info.run_id, "vae/distill"), key=lambda m: m.step)
    first, last = history[0].value, np.mean([m.value for m in history[-3:]])
    assert last < 0.2 * first, [round(m.value, 3) for m in history]
    metrics = pulse.data.metrics
    assert 0.0 <= metrics["eval/success_rate_pulse"] <= 1.0 and metrics["eval/mpjpe_mm"] > 0
    assert metrics["eval/action_error"] < first  # measured on its own evaluation rollouts, after training


def test_only_a_finished_run_is_reused(pipeline):
    uri = pipeline["uri"]
    client = MlflowClient(uri)
    experiment = client.get_experiment_by_name("default").experiment_id
    complete = {"stage_hash": "h-test", "algo": "tracker", "artifacts_sha256": "0" * 64}  # as if all files landed
    for status in ("FAILED", "KILLED"):
        r = client.create_run(experiment, tags=complete)
        client.set_terminated(r.info.run_id, status)
    client.create_run(experiment, tags=complete)  # still RUNNING
    assert find_finished(uri, "h-test", ["default"]) is None
    done = client.create_run(experiment, tags=complete)
    client.set_terminated(done.info.run_id, "FINISHED")
    assert find_finished(uri, "h-test", ["default"]) == done.info.run_id


def test_a_controlvae_posterior_can_be_the_expert(pipeline):
    """The second expert option: demos from a ControlVAE run's posterior (z = μ_q), by `algo.needs.expert`."""
    cfg, uri, root = pipeline["cfg"], pipeline["uri"], pipeline["root"]
    up = stages.ensure(
        "demos", "demos algo.needs.expert=controlvae", cfg, uri, root / "cv", "default", train_stage, print
    )
    demos, manifest = load_demos(up)
    assert manifest["expert_algo"] == "controlvae" and demos.num_episodes == 2
    assert np.isfinite(demos.actions).all() and manifest["expert"]["tracking_error_mean"] > 0


def test_per_clip_experts_one_stage_per_clip_and_the_mirrors_run_mirrored(tmp_path):
    """algo.demos.experts=per_clip (the default) on walk and run, mirrored: one tracker stage per clip, each
    trained on its clip alone, and the demos of all four clips, each mirror's by its clip's expert mirrored;
    the manifest says whose every clip's rollouts are, and how many stayed up."""
    uri = f"sqlite:///{tmp_path / 'store.db'}"
    cfg = smoke_config(tmp_path / "demos", "algo=demos", f"tracking.uri={uri}", "motion=locomotion",
                       "motion.clips=[humanoid3d_walk,humanoid3d_run]")  # fmt: skip
    assert set(stages.needs_of(cfg)) == {"expert.0", "expert.1"}
    run(cfg)
    clips = {r.info.run_id: ast.literal_eval(r.data.params["motion.clips"]) for r in runs_of(uri, "tracker")}
    trackers = {names[0]: run_id for run_id, names in clips.items() if len(names) == 1}
    assert sorted(trackers) == ["humanoid3d_run", "humanoid3d_walk"]
    demos = runs_of(uri, "demos")[0]
    manifest = json.loads((tmp_path / "demos" / "demos" / "manifest.json").read_text())
    per_clip = manifest["per_clip"]
    assert list(per_clip) == ["humanoid3d_walk", "humanoid3d_walk_mirror", "humanoid3d_run", "humanoid3d_run_mirror"]
    for name, clip in per_clip.items():
        assert clip["expert_run"] == trackers[name.removesuffix("_mirror")]
        assert clip["mirrored"] == name.endswith("_mirror") and 0.0 <= clip["stayed_up_fraction"] <= 1.0
    assert set(demos.data.tags["expert_run_id"].split(",")) == set(trackers.values())
    assert "expert/clip/humanoid3d_run_mirror/tracking_error" in demos.data.metrics


def _minutes(cfg, minutes: float):
    """`cfg` with its run's measured minutes set."""
    loop = dataclasses.replace(cfg.algo.loop, expected_minutes=minutes)
    return dataclasses.replace(cfg, algo=dataclasses.replace(cfg.algo, loop=loop))


def test_a_sweep_says_what_it_will_train_and_how_long_it_should_take(pipeline, tmp_path):
    """stages.pending lists what resolve would train (every stage of an empty store, each once, upstream first;
    nothing of a store that holds them) and expected_time adds their measured minutes to the points'."""
    from unittest import mock

    clips = "motion.clips=[humanoid3d_walk,humanoid3d_run]"
    cfg = smoke_config(tmp_path / "pv", "algo=physicsvae", "motion=locomotion", clips)
    empty = f"sqlite:///{tmp_path / 'empty.db'}"
    todo = stages.pending(cfg, empty, "default")
    assert [c.algo.name for c in todo] == ["tracker", "tracker", "demos", "simulation_layer"]
    assert [c.motion.clips for c in todo[:2]] == [["humanoid3d_walk"], ["humanoid3d_run"]]
    minutes = {"tracker": 20.0, "demos": 1.0, "simulation_layer": 5.0}
    with mock.patch.object(stages, "pending", return_value=[_minutes(c, minutes[c.algo.name]) for c in todo]):
        said = stages.expected_time(_minutes(cfg, 10.0), empty, "default", points=6, jobs=2)
    # 2 x 20 + 1 + 5 for the stages, then 6 points two at a time: 3 rounds of 10.
    assert said.startswith("expected time on a 2-core machine: about 76 min (2 tracker stages 40 min; 1 demos")
    assert "6 runs of physicsvae, 2 at a time, 30 min" in said and "not measured" not in said
    unmeasured = stages.expected_time(cfg, empty, "default")
    assert "not measured at scale smoke: tracker, demos, simulation_layer, physicsvae" in unmeasured
    assert stages.pending(pipeline["cfg"], pipeline["uri"], "default") == []  # the pipeline's store holds them all
