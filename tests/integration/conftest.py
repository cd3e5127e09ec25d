"""Runs of the whole service, composed from conf/ exactly as `python -m orchestrator` composes them."""

from __future__ import annotations

import pytest
from stage_runs import smoke_config

from orchestrator.schema import Config


@pytest.fixture
def smoke(tmp_path):
    def make(*overrides: str, name: str = "run") -> Config:
        return smoke_config(tmp_path / name, *overrides)

    return make
