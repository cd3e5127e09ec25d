"""The same loop on Ray actors: two rollout workers, named actors, and a worker that dies and comes back."""

from __future__ import annotations

import os

import pytest

from orchestrator.build import build_runtime
from orchestrator.runtime.cores import available, plan
from orchestrator.tracking.base import NoOpLogger
from orchestrator.trainer import Trainer
from orchestrator.world import load_character_and_library

pytestmark = [pytest.mark.ray, pytest.mark.slow]


class Recorder(NoOpLogger):
    def __init__(self):
        self.metrics: list[tuple[int, dict[str, float]]] = []

    def log_metrics(self, metrics, step):
        self.metrics.append((step, dict(metrics)))


def test_ray_run_matches_local_and_survives_a_killed_worker(smoke):
    import ray

    cfg = smoke("runtime=ray", "runtime.rollout_workers=2", "algo.loop.iterations=10", "algo.loop.checkpoint_every=0")
    character, _ = load_character_and_library(cfg)
    rt = build_runtime(cfg)
    tracker = Recorder()
    try:
        trainer = Trainer(cfg, rt, tracker, character)
        actors = ("replay", "learner-world_model", "learner-vae", "rollout-0", "rollout-1")
        for name in actors:
            assert ray.get_actor(name, namespace=rt.namespace) is not None  # named in the dashboard
        # runtime.pin_cores=auto: the VAE learner, which the loop waits on, has a core of its own where there
        # is one to spare (2 here), and every other actor the rest
        cores = plan(available(), ["learner-vae"], [a for a in actors if a != "learner-vae"])
        for name in actors:
            actor = ray.get_actor(name, namespace=rt.namespace)
            seen = ray.get(actor.__ray_call__.remote(lambda _: sorted(os.sched_getaffinity(0))))
            assert seen == list(cores.get(name, available())), name
        trainer.method.start(trainer)
        first = [trainer.step() for _ in range(3)]
        rt.kill(trainer.workers[0])
        steps = [trainer.step() for _ in range(8)]  # the restart count is refreshed every 10 iterations
        assert steps[-1]["rollout/worker_restarts"] >= 1
        assert all(m["throughput/samples_per_s"] > 0 for m in steps)
        assert trainer.state.samples == 11 * 2 * cfg.runtime.envs_per_worker * cfg.algo.loop.collect_steps
    finally:
        rt.shutdown()
    # The same three iterations in one process give the same numbers: the actors see the same calls in order.
    local_cfg = smoke("runtime=local", "runtime.rollout_workers=2", "algo.loop.checkpoint_every=0", name="local")
    local_rt = build_runtime(local_cfg)
    local = Trainer(local_cfg, local_rt, NoOpLogger(), character)
    local.method.start(local)
    expected = [local.step() for _ in range(3)]
    for key in ("world_model/loss", "vae/rec", "replay/size"):
        assert [m[key] for m in first] == [m[key] for m in expected], key


def test_a_killed_learner_and_replay_come_back_from_the_last_checkpoint(smoke):
    cfg = smoke("runtime=ray", "runtime.rollout_workers=1", "algo.loop.checkpoint_every=0")
    character, _ = load_character_and_library(cfg)
    rt = build_runtime(cfg)
    try:
        trainer = Trainer(cfg, rt, Recorder(), character)
        trainer.method.start(trainer)
        for _ in range(4):
            before = trainer.step()
        assert before["world_model/version"] > 0 and before["loop/recoveries"] == 0
        trainer.save()
        saved_version, saved_size = before["world_model/version"], before["replay/size"]
        rt.kill(trainer.handles["world_model"])
        after = trainer.step()
        # The retried update ran on a fresh learner; the loop saw the new life and reloaded the checkpoint.
        assert after["loop/recoveries"] == 1
        after = trainer.step()
        assert after["world_model/version"] > saved_version  # continues from the checkpoint, not from zero
        rt.kill(trainer.handles["replay"])
        after = trainer.step()
        assert after["loop/recoveries"] == 2
        assert after["replay/size"] >= saved_size  # the buffer came back with what the checkpoint held
        assert trainer.step()["world_model/loss"] > 0
    finally:
        rt.shutdown()


def test_amp_learners_run_as_named_actors_and_come_back_from_the_last_checkpoint(smoke):
    """AMP on Ray: killing learner-discriminator, then learner-ppo, recovers each from the last checkpoint."""
    import ray

    cfg = smoke("algo=amp", "runtime=ray", "runtime.rollout_workers=1", "algo.loop.checkpoint_every=0")
    character, _ = load_character_and_library(cfg)
    rt = build_runtime(cfg)
    try:
        trainer = Trainer(cfg, rt, Recorder(), character)
        for name in ("learner-ppo", "learner-discriminator", "rollout-0"):
            assert ray.get_actor(name, namespace=rt.namespace) is not None
        trainer.method.start(trainer)
        for _ in range(3):
            before = trainer.step()
        assert before["disc/version"] > 0 and before["ppo/version"] > 0 and before["loop/recoveries"] == 0
        trainer.save()
        saved = {k: before[f"{k}/version"] for k in ("disc", "ppo")}
        for recoveries, (key, prefix) in enumerate((("discriminator", "disc"), ("ppo", "ppo")), start=1):
            rt.kill(trainer.handles[key])
            after = trainer.step()
            assert after["loop/recoveries"] == recoveries, key
            after = trainer.step()
            assert after[f"{prefix}/version"] > saved[prefix], key  # continues from the checkpoint
        assert after["ppo/policy_lag"] == 0  # the workers were refreshed to the reloaded policy
    finally:
        rt.shutdown()


def test_the_physicsvae_and_pulse_stages_run_on_ray_actors(smoke, tmp_path):
    """tracker -> demos (collected by the Ray rollout workers) -> simulation_layer -> physicsvae, then pulse on its
    own expert (a tracker observing s_g-mimic), every learner an actor; each stage's run finishes in the
    shared store."""
    from mlflow.tracking import MlflowClient

    from orchestrator.build import run

    uri = f"sqlite:///{tmp_path / 'store.db'}"
    run(smoke("algo=physicsvae", "runtime=ray", f"tracking.uri={uri}", name="physicsvae"))
    run(smoke("algo=pulse", "runtime=ray", f"tracking.uri={uri}", name="pulse"))
    client = MlflowClient(uri)
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    by_algo: dict[str, list] = {}
    for r in runs:
        by_algo.setdefault(r.data.tags["algo"], []).append(r)
    assert {a: len(rs) for a, rs in by_algo.items()} == {
        "tracker": 2,
        "demos": 1,
        "simulation_layer": 1,
        "physicsvae": 1,
        "pulse": 1,
    }
    assert all(r.info.status == "FINISHED" for r in runs)
    assert by_algo["demos"][0].data.metrics["demos/episodes"] == 2  # one clip, two rollouts at smoke scale
    assert "eval/time_until_fall_mean" in by_algo["physicsvae"][0].data.metrics
    assert "eval/success_rate_pulse" in by_algo["pulse"][0].data.metrics


def test_a_task_stage_runs_on_ray_with_either_trainer(smoke, tmp_path):
    """algo=task on Ray actors: the skill stage, then the model-based trainer (learner-task) and PPO (learner-ppo),
    whose workers receive the frozen skill model through `configure` and whose actors read it from the store."""
    from mlflow.tracking import MlflowClient

    from orchestrator.build import run

    uri = f"sqlite:///{tmp_path / 'store.db'}"
    for trainer in ("model", "ppo"):
        overrides = ("algo=task", "runtime=ray", f"algo.task.trainer={trainer}", "algo.loop.iterations=4")
        cfg = smoke(*overrides, f"tracking.uri={uri}", name=trainer)
        run(cfg)
    client = MlflowClient(uri)
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    tasks = [r for r in runs if r.data.tags.get("algo") == "task"]
    assert len(tasks) == 2 and len([r for r in runs if r.data.tags.get("algo") == "controlvae"]) == 1
    for r in tasks:
        assert r.info.status == "FINISHED"
        assert {"eval/task_return", "rollout/task_reward", "skill/tracking_error_mean"} <= r.data.metrics.keys()
