"""What the servo process reports it was granted (hil/servo/rt.py)."""

from __future__ import annotations

from pathlib import Path

from hil.servo.rt import RtGranted, rt_cpu_cap


def test_the_kernels_cap_on_real_time_tasks_is_read_from_proc() -> None:
    runtime_us = int(Path("/proc/sys/kernel/sched_rt_runtime_us").read_text())
    period_us = int(Path("/proc/sys/kernel/sched_rt_period_us").read_text())
    expected = None if runtime_us < 0 else round(runtime_us / period_us, 4)
    assert rt_cpu_cap() == expected


def test_the_summary_names_the_cap_and_a_dict_round_trips() -> None:
    g = RtGranted(requested=True, fifo_priority=80, cpu=1, mlockall=True, gc_frozen=True, rt_cpu_cap=0.95)
    assert g.summary() == ("SCHED_FIFO 80, CPU 1, memory locked, GC frozen, RT tasks capped at 95 % of a CPU")
    assert RtGranted.from_dict(g.to_dict()) == g
    uncapped = RtGranted(requested=True, fifo_priority=80, cpu=1, mlockall=True, gc_frozen=True)
    assert uncapped.summary() == "SCHED_FIFO 80, CPU 1, memory locked, GC frozen"
    refused = RtGranted(requested=True, errors={"fifo": "PermissionError: [Errno 1]"}, rt_cpu_cap=0.95)
    assert refused.summary() == ("no SCHED_FIFO, not pinned, memory not locked, GC running "
                                 "(refused: fifo: PermissionError: [Errno 1])")
