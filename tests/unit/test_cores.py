"""runtime.pin_cores: which actor runs on which core, and a pinned class that really pins its process."""

from __future__ import annotations

import multiprocessing
import os
from types import SimpleNamespace

import pytest

from orchestrator.runtime import cores
from orchestrator.runtime.cores import assign, available, pin, pinned, plan

linux_only = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="CPU affinity is Linux's")


def test_plan_gives_each_critical_actor_a_core_of_its_own_and_the_rest_the_others() -> None:
    assert plan([0, 1], ["vae"], ["replay", "rollout-0"]) == {"vae": (1,), "replay": (0,), "rollout-0": (0,)}
    # 8 cores, two critical actors: the last two cores are theirs, the first six shared
    got = plan(list(range(8)), ["vae", "wm"], ["rollout-0"])
    assert got == {"vae": (6,), "wm": (7,), "rollout-0": (0, 1, 2, 3, 4, 5)}
    # cores as the affinity mask gives them (a container's cpuset need not start at 0)
    assert plan([4, 9], ["vae"], ["replay"]) == {"vae": (9,), "replay": (4,)}


def test_plan_pins_nothing_without_a_core_left_for_the_rest_or_without_a_critical_actor() -> None:
    assert plan([0], ["vae"], ["replay"]) == {}
    assert plan([0, 1], ["vae", "wm"], ["replay"]) == {}
    assert plan([0, 1, 2, 3], [], ["replay"]) == {}


def runtime(**kw) -> SimpleNamespace:
    base = {"_target_": "orchestrator.runtime.ray.RayRuntime", "pin_cores": "auto", "address": None}
    return SimpleNamespace(**{**base, **kw})


@pytest.fixture
def locks(tmp_path, monkeypatch):
    """Claims in a lock directory of this test's own, released after it."""
    monkeypatch.setattr(cores, "LOCK_DIR", tmp_path / "cores")
    yield tmp_path / "cores"
    cores.release()


def test_assign_pins_only_a_ray_started_for_the_run_and_only_when_asked(locks) -> None:
    assert assign(runtime(pin_cores="shared"), ["learner-vae"], ["replay"]) == {}
    assert assign(runtime(address="10.0.0.5:6379"), ["learner-vae"], ["replay"]) == {}  # a shared cluster
    local = runtime(_target_="orchestrator.runtime.local.LocalRuntime")
    assert assign(local, ["learner-vae"], ["replay"]) == {}
    expected = plan(available(), ["learner-vae"], ["replay", "rollout-0"])
    assert assign(runtime(), ["learner-vae"], ["replay", "rollout-0"]) == expected


def _hold(core: int, lock_dir, ready, done) -> None:
    cores.LOCK_DIR = lock_dir
    assert cores.claim([core])
    ready.set()
    done.wait(60)


@linux_only
def test_a_core_another_run_holds_is_left_to_it_and_freed_when_that_run_ends(locks) -> None:
    """Two runs on one machine (a parallel sweep's points): the second sees the first's core as taken and
    plans without it; once the first lets go (or its process ends) the core is free again."""
    mine = available()  # on one core the plans are all {}, and the claims below are still checked
    ctx = multiprocessing.get_context("spawn")
    ready, done = ctx.Event(), ctx.Event()
    other = ctx.Process(target=_hold, args=(mine[-1], locks, ready, done))
    other.start()
    try:
        assert ready.wait(60)
        assert cores.held_elsewhere(mine[-1]) and (len(mine) == 1 or not cores.held_elsewhere(mine[0]))
        expected = plan(mine[:-1], ["learner-vae"], ["replay"])  # {} on 2 cores: one left, none to spare
        assert assign(runtime(), ["learner-vae"], ["replay"]) == expected
    finally:
        done.set()
        other.join(60)
    assert not cores.held_elsewhere(mine[-1])  # the other run's process ended: its core is free
    got = assign(runtime(), ["learner-vae"], ["replay"])
    assert got == plan(mine, ["learner-vae"], ["replay"])
    assert cores.held_elsewhere(mine[-1]) == bool(got)  # held by this run now (when pinned), until release
    assert not got or got["learner-vae"] == (mine[-1],)
    cores.release()
    assert not cores.held_elsewhere(mine[-1])


class Probe:
    """Reports the cores its process may run on, and those of a thread it starts."""

    def __init__(self, label: str):
        self.label = label

    def cores(self) -> tuple[list[int], list[int]]:
        import threading

        seen: list[int] = []
        t = threading.Thread(target=lambda: seen.extend(sorted(os.sched_getaffinity(0))))
        t.start()
        t.join()
        return sorted(os.sched_getaffinity(0)), seen


def _build_pinned(core: int, out) -> None:
    probe = pinned(Probe, [core])("x")
    out.put((type(probe).__name__, probe.label, *probe.cores()))


@linux_only
def test_a_pinned_class_pins_its_process_and_later_threads_before_it_is_built() -> None:
    core = available()[-1]
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=_build_pinned, args=(core, out))
    proc.start()
    name, label, main, thread = out.get(timeout=60)
    proc.join(timeout=60)
    assert (name, label) == ("Probe", "x")  # the same class to Ray's dashboard, built with its arguments
    assert main == [core] and thread == [core]
    assert sorted(os.sched_getaffinity(0)) == available()  # this process is untouched


@linux_only
def test_pin_in_this_process_can_be_undone() -> None:
    before = available()
    try:
        pin(before[:1])
        assert sorted(os.sched_getaffinity(0)) == before[:1]
    finally:
        pin(before)
    assert available() == before
