"""Shared fixtures: the character and small motion libraries, built once per session."""

from __future__ import annotations

import signal

import pytest
import torch

from workers.body.character import Character
from workers.motion.library import MotionLibrary


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """One torch thread for every test: the tests' networks are small, and on a busy two-core
    machine two contending threads were measured up to ten times slower than one."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def pytest_configure(config):
    """Ctrl-C as a terminal gives it, however pytest was started: a non-interactive shell starts a background
    command (`make test &`) with SIGINT ignored, Python keeps that, and every process a test starts inherits
    it, so the tests of Ctrl-C (an in-process shield, a run interrupted in a child) would see it ignored."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def character() -> Character:
    return Character.load()


@pytest.fixture(scope="session")
def clip_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("clip-cache")


@pytest.fixture(scope="session")
def walk_run(character, clip_cache) -> MotionLibrary:
    return MotionLibrary.load(character, ["humanoid3d_walk", "humanoid3d_run"], fps=30, cache_dir=clip_cache)
