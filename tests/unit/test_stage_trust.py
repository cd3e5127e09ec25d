"""Stages reused only from experiments the run trusts, with their provenance; hashes that follow the inputs'
contents and the code's version; stages complete only with their manifest, and their files checked against
it; deleted runs refused; every spec of a chain checked before any stage trains; downloads kept per run;
a store's config that names a class outside our methods refused before its module is imported."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from orchestrator import stages
from orchestrator.compose import compose, validate
from orchestrator.schema import ConfigError
from orchestrator.tracking import manifest
from orchestrator.tracking.query import complete_runs, find_finished
from orchestrator.upstream import StageError, Upstream, existing_run
from workers.motion.formats import resolve


def config(tmp_path, *overrides: str):
    return validate(compose(["scale=smoke", f"run_dir={tmp_path / 'run'}", *overrides]))


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("store")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    client = MlflowClient(uri)
    ids = {name: client.create_experiment(name, artifact_location=str(root / name)) for name in ("mine", "shared")}
    return uri, client, ids


def finished(client, experiment_id: str, stage_hash: str, complete: bool = True, **tags: str) -> str:
    """A FINISHED stage run with a config.json; `complete`: with its manifest and completion tag, as our tracker
    ends a run whose uploads all landed."""
    run = client.create_run(experiment_id, tags={"stage_hash": stage_hash, "algo": "tracker", **tags})
    run_id = run.info.run_id
    client.log_text(run_id, "{}", "config.json")
    if complete:
        text = json.dumps({"config.json": hashlib.sha256(b"{}").hexdigest()})
        client.log_text(run_id, text, manifest.MANIFEST_FILE)
        client.set_tag(run_id, manifest.COMPLETE_TAG, manifest.text_digest(text))
    client.set_terminated(run_id, "FINISHED")
    return run_id


def stored_file(client, run_id: str, path: str) -> Path:
    """Where a SQLite store keeps run `run_id`'s artifact `path` (to spoil it as a bad disk would)."""
    return Path(client.get_run(run_id).info.artifact_uri.removeprefix("file://")) / path


def test_a_stage_whose_files_did_not_all_land_is_skipped_for_the_newest_complete_one(store):
    uri, client, ids = store
    older = finished(client, ids["mine"], "h-partial")
    finished(client, ids["mine"], "h-partial", complete=False)  # newer, FINISHED, its uploads still spooled
    assert find_finished(uri, "h-partial", ["mine"]) == older
    assert [r for r, _ in complete_runs(uri, "h-partial", ["mine"])] == [older]


def test_a_stage_artifact_changed_in_the_store_is_named_and_the_older_verified_run_is_used(store, tmp_path):
    uri, client, ids = store
    cfg = config(tmp_path, "algo=demos")
    up = stages.upstream_config(cfg, "tracker", "expert")
    h = stages.config_hash(up)
    good = finished(client, ids["mine"], h)
    spoiled = finished(client, ids["mine"], h)
    stored_file(client, spoiled, "config.json").write_text('{"planted": 1}')
    lines: list[str] = []
    never = lambda *a: pytest.fail("trained")  # noqa: E731
    used = stages.ensure("expert", "tracker", cfg, uri, tmp_path, "mine", never, lines.append)
    assert used.run_id == good and used.reused
    assert lines[0] == (
        f"stage expert (tracker, run {spoiled}): artifact config.json does not match its SHA-256 in "
        "artifacts.sha256.json (changed since the run); not used"
    ), lines
    # Read later by a consumer (an actor on another node, say), a file changed meanwhile is refused too.
    stored_file(client, good, "config.json").write_text("{ }")
    fresh = Upstream("expert", "tracker", good, h, uri, tmp_path / "other", True, manifest_digest=used.manifest_digest)
    with pytest.raises(StageError, match=r"artifact config.json does not match its SHA-256"):
        fresh.artifact("config.json")


def test_a_deleted_run_is_refused_as_a_stage(store, tmp_path):
    uri, client, ids = store
    run_id = finished(client, ids["mine"], "h-deleted")
    client.delete_run(run_id)
    assert find_finished(uri, "h-deleted", ["mine"]) is None
    with pytest.raises(StageError, match=rf"stage expert: run {run_id} is DELETED, not FINISHED"):
        existing_run("expert", run_id, uri, tmp_path)


def test_a_finished_run_in_another_experiment_is_found_only_where_trusted(store):
    uri, client, ids = store
    planted = finished(client, ids["shared"], "h-planted")
    assert find_finished(uri, "h-planted", ["mine"]) is None
    assert find_finished(uri, "h-planted", ["mine", "no-such-experiment"]) is None
    assert find_finished(uri, "h-planted", ["mine", "shared"]) == planted
    assert find_finished(uri, "h-planted", ["*"]) == planted


def test_a_stage_planted_in_a_shared_experiment_is_trained_again_not_reused(store, tmp_path):
    uri, client, ids = store
    cfg = config(tmp_path, "algo=demos")
    up = stages.upstream_config(cfg, "tracker", "expert")
    h = stages.config_hash(up)
    planted = finished(client, ids["shared"], h, git_commit="abc123")
    trained: list[str] = []

    def train(stage_cfg, above, stage_hash):
        trained.append(stage_hash)
        return finished(client, ids["mine"], stage_hash, git_commit="def456")

    fresh = stages.ensure("expert", "tracker", cfg, uri, tmp_path, "mine", train, log=lambda m: None)
    assert trained == [h] and fresh.run_id != planted and not fresh.reused
    assert fresh.provenance["experiment"] == "mine" and fresh.provenance["git_commit"] == "def456"

    # Named in tracking.reuse_from, the other experiment is trusted: the newest match there or here is reused.
    trusting = config(tmp_path, "algo=demos", "tracking.reuse_from=[shared]")
    client.delete_run(fresh.run_id)
    reused = stages.ensure("expert", "tracker", trusting, uri, tmp_path, "mine", train, log=lambda m: None)
    assert reused.run_id == planted and reused.reused and trained == [h]
    tags = stages.lineage_tags({"expert": reused})
    assert tags["upstream.expert"] == planted
    assert tags["upstream.expert.experiment"] == "shared" and tags["upstream.expert.git_commit"] == "abc123"
    assert tags["upstream.expert.user"] and tags["expert_run_id"] == planted


def test_the_stage_hash_follows_the_contents_of_the_clips_and_the_character(tmp_path):
    clip = tmp_path / "walk.txt"
    shutil.copy(resolve("humanoid3d_walk"), clip)
    hashes = [stages.config_hash(config(tmp_path, f"motion.clips=[{clip}]"))]
    clip.write_text(clip.read_text() + "\n")  # the same path, other contents
    hashes.append(stages.config_hash(config(tmp_path, f"motion.clips=[{clip}]")))
    character = tmp_path / "humanoid.xml"
    shutil.copy(resolve_character(), character)
    hashes.append(stages.config_hash(config(tmp_path, f"motion.clips=[{clip}]", f"character.xml={character}")))
    character.write_text(character.read_text() + "\n<!-- edited -->\n")
    hashes.append(stages.config_hash(config(tmp_path, f"motion.clips=[{clip}]", f"character.xml={character}")))
    hashes.append(stages.config_hash(config(tmp_path, f"motion.clips=[{clip}]", "tracking.stage_code=commit")))
    assert len(set(hashes)) == len(hashes), hashes
    # What does not decide the result still leaves it alone.
    assert stages.config_hash(config(tmp_path, f"motion.clips=[{clip}]", "tracking.reuse_from=[x]")) == hashes[1]


def test_the_stage_hash_follows_the_simulator_engine_and_stages_above_run_on_the_same(tmp_path):
    pytest.importorskip("mujoco_warp")
    c_engine = stages.config_hash(config(tmp_path))
    warp = config(tmp_path, "sim.backend=warp")
    assert stages.config_hash(warp) != c_engine  # float32 physics: another result
    assert stages.config_hash(config(tmp_path, "sim.backend=warp", "sim.device=cuda")) == stages.config_hash(warp)
    assert stages.config_hash(config(tmp_path, "sim.device=cuda")) == c_engine  # MuJoCo C ignores the device
    expert = stages.upstream_config(warp, "tracker", "expert")
    assert expert.sim.backend == "warp" and expert.algo.name == "tracker"


def test_the_stage_hash_follows_the_source_of_the_code_that_computes_stages(tmp_path):
    """A change to a loss changes the code digest a stage hash holds (the default, tracking.stage_code=source);
    a change to code that computes no stage (the sweep's report) does not."""
    from orchestrator import provenance

    for name in ("workers", "orchestrator"):
        shutil.copytree(provenance.ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    before = provenance.source_digest(tmp_path)
    assert before == provenance.source_digest(provenance.ROOT)  # by relative path and contents only
    report = tmp_path / "orchestrator" / "sweep" / "report.py"
    report.write_text(report.read_text() + "\n# a comment\n")
    assert provenance.source_digest(tmp_path) == before
    kl = tmp_path / "workers" / "losses" / "kl.py"
    kl.write_text(kl.read_text().replace("0.5", "0.49", 1))
    assert provenance.source_digest(tmp_path) != before
    cfg = config(tmp_path)
    assert cfg.tracking.stage_code == "source"
    assert stages.config_hash(cfg) != stages.config_hash(config(tmp_path, "tracking.stage_code=version"))


def resolve_character():
    from workers.body.character import HUMANOID_XML

    return HUMANOID_XML


def test_every_spec_of_the_chain_is_checked_before_any_stage_trains(store, tmp_path):
    uri = store[0]
    trained: list[str] = []
    # physicsvae needs demos (from a tracker), then a world_model stage, whose own demos need is broken here:
    # resolved in turn, the tracker and the demos would train before the bad spec is met.
    cfg = config(tmp_path, "algo=physicsvae", '+stage_overrides.simulation_layer=["algo.needs.demos=nosuchmethod"]')
    with pytest.raises(ConfigError, match=r"algo.needs.demos: cannot compose stage 'nosuchmethod'"):
        stages.resolve(cfg, uri, tmp_path, "mine", lambda c, a, h: trained.append(h), log=lambda m: None)
    assert trained == []
    with pytest.raises(ConfigError, match="tracking.stage_code must be one of source, version, commit"):
        config(tmp_path, "tracking.stage_code=sometimes")


def test_downloads_are_kept_per_run_so_another_run_is_never_served_a_stale_file(store, tmp_path):
    uri, client, ids = store
    runs = []
    for value in ("first", "second"):
        run_id = finished(client, ids["mine"], f"h-{value}")
        client.log_text(run_id, value, "notes.txt")
        runs.append(run_id)
    cache = tmp_path / "upstream" / "expert"  # one role, the same directory, two runs in turn
    texts = [Upstream("expert", "tracker", r, "h", uri, cache, True).artifact("notes.txt").read_text() for r in runs]
    assert texts == ["first", "second"]


def test_a_stored_config_naming_a_class_outside_our_methods_is_refused_before_its_module_loads(tmp_path, monkeypatch):
    module = tmp_path / "planted_module.py"
    marker = tmp_path / "imported"
    module.write_text(f"open({str(marker)!r}, 'w').close()\nclass Evil: pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    stored = json.loads(json.dumps(_plain(config(tmp_path))))
    stored["algo"]["_target_"] = "planted_module.Evil"
    with pytest.raises(
        ConfigError, match=r"algo._target_: 'planted_module.Evil' is not one of the methods in conf/algo"
    ):
        validate(stored, shipped_only=True)
    assert not marker.exists() and "planted_module" not in sys.modules
    stored["algo"]["_target_"] = "orchestrator.algos.controlvae.ControlVAE"
    assert validate(stored, shipped_only=True).algo.name == "controlvae"


def _plain(cfg):
    from dataclasses import asdict

    return asdict(cfg)
