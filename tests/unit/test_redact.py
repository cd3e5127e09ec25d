"""A tracking URI's credentials are masked wherever the URI can leave the process: printed, logged, in params,
tags and text artifacts (orchestrator.tracking.uri; the tracker on a real SQLite store)."""

from __future__ import annotations

import logging
import os
from dataclasses import asdict

import pytest
from mlflow.tracking import MlflowClient

from orchestrator.compose import compose, validate
from orchestrator.console import mlflow_line
from orchestrator.schema import ConfigError
from orchestrator.tracking.base import flatten
from orchestrator.tracking.mlflow import MlflowLogger
from orchestrator.tracking.uri import (
    credentials_to_env,
    hide,
    redact,
    scrub,
    scrub_tree,
    tracking_uri_error,
    uri_secrets,
)


@pytest.mark.parametrize(
    ("uri", "shown"),
    [
        ("postgresql://user:s3cret@db.lab:5432/mlflow", "postgresql://user:***@db.lab:5432/mlflow"),
        ("postgresql+psycopg2://u:p%40ss@h/db?sslmode=require", "postgresql+psycopg2://u:***@h/db?sslmode=require"),
        ("http://alice:pw@127.0.0.1:5000", "http://alice:***@127.0.0.1:5000"),
        ("mysql://h/db?x=1&password=hunter22", "mysql://h/db?x=1&password=***"),
        ("https://h/api?access_token=abc123", "https://h/api?access_token=***"),
        ("sqlite:////runs/mlflow.db", "sqlite:////runs/mlflow.db"),  # no credential: untouched, slashes and all
        ("http://user@host:5000", "http://user@host:5000"),
        ("databricks", "databricks"),
    ],
)
def test_redact_masks_the_password_and_secret_query_values_only(uri, shown):
    assert redact(uri) == shown


def test_the_secrets_of_a_uri_are_its_password_as_written_and_decoded():
    assert uri_secrets("postgresql://u:p%40ss@h/db") == {"p%40ss", "p@ss"}
    assert uri_secrets("mysql://h/db?password=hunter22&user=bob") == {"hunter22"}
    assert uri_secrets("sqlite:///x.db") == set() and uri_secrets(None) == set()


def test_scrub_masks_any_uri_password_in_text_and_the_hidden_secrets_anywhere():
    text = "overrides: [tracking.uri=postgresql://u:zz9q@h/db, seed=1] and http://a:b@c:1/x"
    assert scrub(text) == "overrides: [tracking.uri=postgresql://u:***@h/db, seed=1] and http://a:***@c:1/x"
    # Hydra's launcher logs each point's overrides with the colons escaped.
    assert (
        scrub(r"#0 : tracking.uri=http\://u\:pw@127.0.0.1\:5000 seed=0")
        == r"#0 : tracking.uri=http\://u\:***@127.0.0.1\:5000 seed=0"
    )
    hide("postgresql://u:Opaque%2F77@h/db")
    # Decoded, outside any URI (as a driver's error message may quote it): masked once hidden.
    assert scrub("auth failed for password Opaque/77") == "auth failed for password ***"
    assert scrub_tree({"a": ["x Opaque%2F77", ("Opaque/77",)], "n": 3}) == {"a": ["x ***", ("***",)], "n": 3}


def test_a_hidden_secret_is_masked_in_log_records_and_their_tracebacks(caplog):
    hide("http://bob:Kx81wq@127.0.0.1:1")
    logger = logging.getLogger("test_redact")
    with caplog.at_level(logging.INFO, logger="test_redact"):
        logger.info("connecting to %s", "http://bob:Kx81wq@127.0.0.1:1")
        try:
            raise RuntimeError("refused: Kx81wq")
        except RuntimeError:
            logger.exception("failed")
    assert "Kx81wq" not in caplog.text
    assert "http://bob:***@127.0.0.1:1" in caplog.text and "RuntimeError: refused: ***" in caplog.text


def test_a_config_with_a_password_in_its_uri_gives_params_and_a_console_line_without_it(tmp_path):
    uri = "postgresql://user:Vq7p2LmN@db.lab:5432/mlflow"
    cfg = validate(compose(["scale=smoke", f"run_dir={tmp_path}", f"tracking.uri={uri}"]))
    params = flatten(scrub_tree(asdict(cfg)))
    assert params["tracking.uri"] == "postgresql://user:***@db.lab:5432/mlflow"
    assert "Vq7p2LmN" not in repr(params) and "Vq7p2LmN" not in mlflow_line(cfg, "r1")
    problem = tracking_uri_error("nosuch://u:Vq7p2LmN@h")  # the config error line names the URI
    assert "'nosuch://u:***@h'" in problem and "Vq7p2LmN" not in problem


def test_an_http_uri_without_a_host_is_refused():
    """`http:/host` parses as a path with no host: the run would train with every record spooled for ever."""
    assert (
        tracking_uri_error("http:/127.0.0.1:5000")
        == "'http:/127.0.0.1:5000' names no host (a server is http://HOST:PORT)"
    )
    assert tracking_uri_error("http://127.0.0.1:5000") is None


def test_bad_artifact_settings_are_refused_with_the_key_named(tmp_path):
    with pytest.raises(ConfigError, match="tracking.artifact_timeout_s"):
        validate(compose(["scale=smoke", f"run_dir={tmp_path}", "tracking.artifact_timeout_s=0"]))


def test_the_tracker_writes_no_credential_of_its_store_in_params_tags_or_text(tmp_path):
    """A real tracker on a SQLite store; the values it is handed carry the password of a (pretend) server URI."""
    secret_uri = "http://carol:Wz4Tq9vB@mlflow.lab:5000"
    hide(secret_uri)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tracker = MlflowLogger(uri, "redact", run_dir=tmp_path / "run", tags={"origin": secret_uri})
    tracker.log_params({"tracking.uri": secret_uri, "note": "pw Wz4Tq9vB"})
    tracker.set_tags({"server": secret_uri})
    tracker.log_dict({"tracking": {"uri": secret_uri}}, "config.json")
    tracker.log_text(f"- tracking.uri={secret_uri}\n", "hydra/overrides.yaml")
    tracker.close()
    run = MlflowClient(uri).get_run(tracker.run_id)
    assert run.data.params["tracking.uri"] == "http://carol:***@mlflow.lab:5000"
    assert run.data.params["note"] == "pw ***" and run.data.tags["server"] == run.data.tags["origin"]
    stored = [p for p in (tmp_path / "mlartifacts").rglob("*") if p.is_file()]
    assert {p.name for p in stored} == {"artifacts.sha256.json", "config.json", "overrides.yaml"}
    assert all("Wz4Tq9vB" not in p.read_text() for p in stored)
    assert "carol:***@" in next(p for p in stored if p.name == "overrides.yaml").read_text()
    assert b"Wz4Tq9vB" not in (tmp_path / "mlflow.db").read_bytes()


def test_an_http_servers_credentials_go_to_mlflows_environment_variables(monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_USERNAME", raising=False)
    monkeypatch.delenv("MLFLOW_TRACKING_PASSWORD", raising=False)
    assert credentials_to_env("http://dan:p%40ss9@127.0.0.1:5000") == "http://127.0.0.1:5000"
    assert (os.environ["MLFLOW_TRACKING_USERNAME"], os.environ["MLFLOW_TRACKING_PASSWORD"]) == ("dan", "p@ss9")
    # Other credentials already set there win: this URI keeps its own (masked wherever it is shown).
    assert credentials_to_env("http://eve:other@h:1") == "http://eve:other@h:1"
    assert credentials_to_env("postgresql://u:pw@h/db") == "postgresql://u:pw@h/db"  # a database reads its URI
