"""Stages trusted by who wrote them, as an authenticated MLflow server says (MLflow's basic-auth app, started here on
127.0.0.1 with two users): a run another user planted under the preset's experiment is never reused, and a run in
that experiment is refused before anything trains, in one line naming the experiment and the user; in a user's own
experiment only their runs count; an experiment named in `tracking.reuse_from` is trusted whoever wrote it, and the
line that reuses its run says whose it is."""

from __future__ import annotations

import hashlib
import json

import pytest
from mlflow.tracking import MlflowClient
from test_bad_input import assert_refused, run_main  # beside this file (pytest puts its folder on sys.path)

from orchestrator import preflight, stages
from orchestrator.compose import compose, validate
from orchestrator.preflight import InputError
from orchestrator.sweep.callback import refuse_unwritable
from orchestrator.tracking import manifest, mlflow_auth
from orchestrator.tracking.server import start_local_server

USERS = {"alice": "alice-password-for-this-test", "bob": "bob-password-for-this-test"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("trust")
    mlflow_auth.require_auth_app()
    server = start_local_server(f"sqlite:///{root / 'mlflow.db'}", root / "artifacts", auth=True)
    admin = server.credentials["MLFLOW_TRACKING_PASSWORD"]
    for user, password in USERS.items():
        mlflow_auth.ensure_user(server.uri, admin, user, password)
    yield server.uri, admin
    server.stop()


def as_user(monkeypatch, uri: str, user: str) -> MlflowClient:
    """This process logged in as `user`, and a client of theirs."""
    monkeypatch.setenv("MLFLOW_TRACKING_USERNAME", user)
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", USERS[user])
    return MlflowClient(uri)


def complete_run(client: MlflowClient, experiment_id: str, stage_hash: str, user: str) -> str:
    """A FINISHED stage run recorded as `user`'s, with a config.json, its manifest and the completion tag: all that
    our tracker leaves, so that only who wrote it tells it from one of ours."""
    tags = {"stage_hash": stage_hash, "algo": "tracker", "mlflow.user": user, "git_commit": f"{user}-commit"}
    run_id = client.create_run(experiment_id, tags=tags).info.run_id
    client.log_text(run_id, "{}", "config.json")
    text = json.dumps({"config.json": hashlib.sha256(b"{}").hexdigest()})
    client.log_text(run_id, text, manifest.MANIFEST_FILE)
    client.set_tag(run_id, manifest.COMPLETE_TAG, manifest.text_digest(text))
    client.set_terminated(run_id, "FINISHED")
    return run_id


def demos_config(tmp_path, uri: str, *overrides: str):
    return validate(
        compose(["scale=smoke", "algo=demos", f"run_dir={tmp_path / 'run'}", f"tracking.uri={uri}", *overrides])
    )


def expert_hash(cfg) -> str:
    return stages.config_hash(stages.upstream_config(cfg, "tracker", "expert"))


def test_a_stage_planted_by_another_user_under_the_presets_name_is_not_reused_and_the_run_is_refused(
    server, tmp_path, capsys, monkeypatch
):
    uri, _ = server
    cfg = demos_config(tmp_path, uri)
    bob = as_user(monkeypatch, uri, "bob")
    planted = complete_run(bob, bob.create_experiment("default"), expert_hash(cfg), "alice")  # even named as hers

    as_user(monkeypatch, uri, "alice")
    trust = stages.trusted_sources(cfg, uri, "default")
    assert trust.experiments == [] and "not alice's (the server gives them READ on it, not MANAGE)" in trust.note
    never = lambda *a: pytest.fail("trained")  # noqa: E731
    with pytest.raises(InputError) as refused:
        preflight.own_experiment(uri, "default")
    assert str(refused.value) == (
        f"tracking.experiment='default': user 'alice' may not create runs in it on {uri} (the server gives READ; "
        "another user made it): name an experiment of your own, and this one in tracking.reuse_from to reuse its stages"
    )
    with pytest.raises(SystemExit) as exit_:  # a sweep's parent run, before any point starts
        refuse_unwritable(uri, "default")
    assert exit_.value.code == 2 and capsys.readouterr().err == f"error: {refused.value}\n"
    # The command stops there, before any stage is looked up or trained, its run never created.
    code, err = run_main(tmp_path, capsys, "algo=demos", f"tracking.uri={uri}")
    assert_refused(tmp_path, code, err, "tracking.experiment='default'", "user 'alice'")
    assert not (tmp_path / "run").exists()
    assert [r.info.run_id for r in bob.search_runs([bob.get_experiment_by_name("default").experiment_id])] == [planted]

    # Named in tracking.reuse_from, bob's experiment is trusted, and the line says whose the run is.
    lines: list[str] = []
    trusting = demos_config(tmp_path, uri, "tracking.reuse_from=[default]")
    used = stages.ensure("expert", "tracker", trusting, uri, tmp_path, "alice-own", never, lines.append)
    assert used.run_id == planted and used.reused
    assert "of experiment 'default' (named in tracking.reuse_from), user alice, commit alice-commit" in lines[-1]


def test_in_a_users_own_experiment_only_their_runs_are_reused(server, tmp_path, monkeypatch):
    uri, admin = server
    cfg = demos_config(tmp_path, uri)
    h = expert_hash(cfg)
    alice = as_user(monkeypatch, uri, "alice")
    mine = alice.create_experiment("alice-stages")
    # The admin lets bob write to alice's experiment; he leaves a run there, recorded as his.
    grant = {"username": "bob", "resource_type": "experiment", "resource_id": mine, "permission": "EDIT"}
    status, text = mlflow_auth._call(uri, "POST", "/api/3.0/mlflow/users/permissions/grant", ("admin", admin), grant)
    assert status == 200, text
    bob = as_user(monkeypatch, uri, "bob")
    bobs = complete_run(bob, mine, h, "bob")

    alice = as_user(monkeypatch, uri, "alice")
    trust = stages.trusted_sources(cfg, uri, "alice-stages")
    assert trust.experiments == ["alice-stages"] and trust.only == {"alice-stages": "alice"}
    trained: list[str] = []

    def train(stage_cfg, above, stage_hash):
        trained.append(stage_hash)
        return complete_run(alice, mine, stage_hash, "alice")

    lines: list[str] = []
    fresh = stages.ensure("expert", "tracker", cfg, uri, tmp_path, "alice-stages", train, lines.append)
    assert trained == [h] and fresh.run_id != bobs and not fresh.reused
    assert "in experiment(s) 'alice-stages' (runs by alice) of" in lines[-1]
    again = stages.ensure("expert", "tracker", cfg, uri, tmp_path / "again", "alice-stages", train, lines.append)
    assert again.run_id == fresh.run_id and again.reused and trained == [h]
    assert ", user alice, commit alice-commit" in lines[-1] and "reuse_from" not in lines[-1]
