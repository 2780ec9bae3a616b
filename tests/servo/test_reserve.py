"""Keeping this process off the servo loop's CPU (hil/servo/reserve.py): every thread moves, threads
started afterwards inherit it, reservations are counted, and the last release restores the mask
the process had; with no other CPU left nothing changes."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator

import pytest

from hil.servo.reserve import release_cpu, reserve_cpu, reserved_cpus


def _thread_cpus() -> dict[int, set[int]]:
    return {int(t): os.sched_getaffinity(int(t)) for t in os.listdir("/proc/self/task")}


@pytest.fixture
def idle_thread() -> Iterator[threading.Thread]:
    """A thread started before the reservation (it must move too)."""
    done = threading.Event()
    t = threading.Thread(target=done.wait, name="idle", daemon=True)
    t.start()
    try:
        yield t
    finally:
        done.set()
        t.join(5.0)


def test_every_thread_moves_off_the_cpu_and_back(idle_thread: threading.Thread) -> None:
    before = os.sched_getaffinity(0)
    loop_cpu = max(before)
    moved = reserve_cpu(loop_cpu)
    try:
        if len(before) < 2:   # nowhere to go: nothing changes
            assert moved is None
            assert reserved_cpus() == frozenset()
            assert all(cpus == before for cpus in _thread_cpus().values())
            return
        assert moved == frozenset(before - {loop_cpu})
        assert reserved_cpus() == frozenset({loop_cpu})
        assert all(cpus == set(moved) for cpus in _thread_cpus().values())   # the idle thread too
        seen: list[set[int]] = []
        later = threading.Thread(target=lambda: seen.append(os.sched_getaffinity(0)))
        later.start()
        later.join(5.0)
        assert seen == [set(moved)]   # a thread started afterwards inherits it
    finally:
        release_cpu(loop_cpu)
    assert reserved_cpus() == frozenset()
    assert all(cpus == before for cpus in _thread_cpus().values())


def test_reservations_are_counted_and_a_foreign_release_does_nothing() -> None:
    before = os.sched_getaffinity(0)
    if len(before) < 2:
        assert reserve_cpu(max(before)) is None
        return
    loop_cpu, other = max(before), min(before)
    assert reserve_cpu(loop_cpu) is not None
    try:
        assert reserve_cpu(loop_cpu) is not None
        release_cpu(loop_cpu)
        assert os.sched_getaffinity(0) == before - {loop_cpu}   # one loop still runs there
        release_cpu(other)   # never reserved: nothing happens
        assert os.sched_getaffinity(0) == before - {loop_cpu}
    finally:
        release_cpu(loop_cpu)
    assert os.sched_getaffinity(0) == before
    release_cpu(loop_cpu)   # one release too many: nothing happens
    assert os.sched_getaffinity(0) == before
