"""Shared fixtures: the character and small motion libraries, built once per session."""

from __future__ import annotations

import pytest

from workers.motion.library import MotionLibrary
from workers.sim.character import Character


@pytest.fixture(scope="session")
def character() -> Character:
    return Character.load()


@pytest.fixture(scope="session")
def clip_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("clip-cache")


@pytest.fixture(scope="session")
def walk_run(character, clip_cache) -> MotionLibrary:
    return MotionLibrary.load(character, ["humanoid3d_walk", "humanoid3d_run"], fps=30, cache_dir=clip_cache)
