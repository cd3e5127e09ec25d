"""Runs of the whole service, composed from conf/ exactly as `python -m orchestrator` composes them."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from orchestrator.schema import Config, register, validate

CONF = Path(__file__).resolve().parents[2] / "conf"
register()


def smoke_config(run_dir: Path, *overrides: str) -> Config:
    # Tests run single-process (runtime=local) unless they ask for Ray; `python -m orchestrator` defaults to Ray.
    local = [] if any(o.startswith("runtime=") for o in overrides) else ["runtime=local"]
    # Videos cost seconds per evaluation in software GL: only the tests that ask for them render them.
    local += [] if any(o.startswith("eval.video=") for o in overrides) else ["eval.video=false"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=["scale=smoke", "motion=walk", f"run_dir={run_dir}", "progress=false", *local, *overrides],
        )
    return validate(cfg)


@pytest.fixture
def smoke(tmp_path):
    def make(*overrides: str, name: str = "run") -> Config:
        return smoke_config(tmp_path / name, *overrides)

    return make
