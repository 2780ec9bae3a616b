"""Probe what this machine grants a real-time loop, without the project's code in the loop: a fixed
piece of work every period, with the servo process's own real-time set-up (SCHED_FIFO, the loop's
CPU, memory locked, the garbage collector frozen; hil/servo/rt.py) and its sleep-then-spin wait.

Run: ``tools/bench host [--seconds S] [--rate HZ] [--work-ms MS] [--json]``

The work (numpy and Python arithmetic like a servo step's, sized at start to ``--work-ms`` of CPU)
is the same every period, so any period it takes longer is the machine's doing: on a virtual
machine the host runs other guests on the CPU behind ours (*steal*), and a SCHED_FIFO thread
inside the guest cannot prevent it. Printed, per period: the work's wall time and its CPU time
(``CLOCK_THREAD_CPUTIME_ID``, which on a guest with steal accounting leaves out what the host
took), how many periods the work took over twice its median and over a whole period, wake-ups
more than a period late, intervals over two periods (the soak's *late*), and the steal of the CPU
over the run (``/proc/stat``). Read ``hil soak`` figures beside it: a late share the probe shows
too is the machine's; what the soak adds on top is ours. Needs Linux; without root it runs
unprivileged and says so.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

import numpy as np

from hil.servo.rt import apply_realtime, default_cpu, wait_until
from hil.soak.host import sample_steal, steal_percent

#: the servo process's priority (hil/servo/process.py ``ServoSpec.priority``)
PRIORITY = 80
CALIBRATION_RUNS = 50


def _unit(a: Any, b: Any) -> float:
    """One unit of fixed work: a 6x6 solve, a 3x3 product and Python float arithmetic (~20 us)."""
    q = np.linalg.solve(a, b)
    r = a[:3, :3] @ a[:3, :3].T
    return float(q[0]) + float(r[0, 0])


def size_work(work_ms: float) -> int:
    """How many units make ``work_ms`` of CPU time (the median of :data:`CALIBRATION_RUNS`)."""
    a = np.random.default_rng(0).normal(size=(6, 6)) + 6.0 * np.eye(6)
    b = np.ones(6)
    per_unit = []
    for _ in range(CALIBRATION_RUNS):
        t0 = time.thread_time_ns()
        for _ in range(20):
            _unit(a, b)
        per_unit.append((time.thread_time_ns() - t0) / 20)
    return max(1, round(work_ms * 1e6 / float(np.median(per_unit))))


def probe(seconds: float, rate_hz: float, units: int) -> dict[str, Any]:
    """Run the fixed work every period for ``seconds``; the figures (module doc). Blocks."""
    a = np.random.default_rng(0).normal(size=(6, 6)) + 6.0 * np.eye(6)
    b = np.ones(6)
    period_ns = round(1e9 / rate_hz)
    n = int(seconds * rate_hz)
    wall = np.zeros(n, dtype=np.int64)
    cpu = np.zeros(n, dtype=np.int64)
    wake = np.zeros(n, dtype=np.int64)
    starts = np.zeros(n, dtype=np.int64)
    next_ns = time.monotonic_ns() + period_ns
    for k in range(n):
        now = wait_until(next_ns)
        c0 = time.thread_time_ns()
        for _ in range(units):
            _unit(a, b)
        done = time.monotonic_ns()
        wall[k], cpu[k], wake[k], starts[k] = done - now, time.thread_time_ns() - c0, now - next_ns, now
        next_ns += period_ns
        if done - next_ns > period_ns:   # as the servo loop: skip missed slots, never bunch them
            next_ns += ((done - next_ns) // period_ns) * period_ns
    return figures(wall, cpu, wake, starts, period_ns)


def figures(wall_ns: Any, cpu_ns: Any, wake_ns: Any, starts_ns: Any, period_ns: int) -> dict[str, Any]:
    """The probe's figures from its per-period arrays (ns): work wall and CPU time, wake-up delay,
    start times; ``period_ns`` the period."""
    def ms(v: float) -> float:
        return round(v * 1e-6, 3)
    med = float(np.median(wall_ns))
    intervals = np.diff(starts_ns)
    late = int((intervals > 2 * period_ns).sum())
    return {
        "periods": int(wall_ns.size),
        "work_wall_ms": {"p50": ms(med), "p99": ms(float(np.percentile(wall_ns, 99))),
                         "max": ms(float(wall_ns.max()))},
        "work_cpu_ms": {"p50": ms(float(np.median(cpu_ns))), "max": ms(float(cpu_ns.max()))},
        "stretched_over_2x": int((wall_ns > 2 * med).sum()),
        "work_over_a_period": int((wall_ns > period_ns).sum()),
        "woke_late": int((wake_ns > period_ns).sum()),
        "longest_wake_delay_ms": ms(float(wake_ns.max())),
        "intervals": int(intervals.size),
        "late": late,
        "late_fraction": round(late / intervals.size, 6) if intervals.size else 0.0,
        "longest_interval_ms": ms(float(intervals.max())) if intervals.size else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench host", description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="how long to probe, s (default 30)")
    ap.add_argument("--rate", type=float, default=500.0, help="periods per second, Hz (default 500)")
    ap.add_argument("--work-ms", type=float, default=0.5,
                    help="CPU time of the fixed work per period, ms (default 0.5: a simulated servo step)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    if not (args.seconds > 0 and args.rate > 0 and 0 < args.work_ms < 1e3 / args.rate):
        print(f"tools/bench host: need seconds > 0, rate > 0 and 0 < work-ms < the period "
              f"(got {args.seconds}, {args.rate}, {args.work_ms})", file=sys.stderr)
        return 2
    cpu = default_cpu()
    granted = apply_realtime(PRIORITY, cpu)
    units = size_work(args.work_ms)
    s0, a0 = sample_steal(cpu), sample_steal(None)
    out = probe(args.seconds, args.rate, units)
    s1, a1 = sample_steal(cpu), sample_steal(None)
    out.update({"rate_hz": args.rate, "work_units": units, "rt_granted": granted.to_dict(), "cpu": cpu,
                "host_steal_percent": {
                    "loop_cpu": steal_percent(s0, s1) if s0 and s1 else None,
                    "all_cpus": steal_percent(a0, a1, os.cpu_count() or 1) if a0 and a1 else None}})
    if args.json:
        print(json.dumps(out))
    else:
        _print(out, args, granted.summary())
    return 0


def _print(out: dict[str, Any], args: argparse.Namespace, granted: str) -> None:
    w, c = out["work_wall_ms"], out["work_cpu_ms"]
    n = out["periods"]
    steal = out["host_steal_percent"]
    print(f"host probe: {args.work_ms:g} ms of fixed work every {1e3 / args.rate:g} ms on CPU {out['cpu']} "
          f"for {args.seconds:g} s ({granted})")
    print(f"work wall p50/p99/max  {w['p50']} / {w['p99']} / {w['max']} ms "
          f"(its CPU time p50/max {c['p50']} / {c['max']} ms)")
    print(f"stretched              {out['stretched_over_2x']} of {n} periods over twice the median "
          f"({100 * out['stretched_over_2x'] / n:.2f} %), {out['work_over_a_period']} over a period")
    print(f"woke late              {out['woke_late']} over a period late, "
          f"longest {out['longest_wake_delay_ms']} ms")
    per_10k = 1e4 * out["late"] / max(out["intervals"], 1)
    print(f"late intervals         {out['late']} of {out['intervals']} over two periods "
          f"({per_10k:.1f} in 10,000), longest {out['longest_interval_ms']} ms")
    print(f"host steal             {steal['loop_cpu']} % of CPU {out['cpu']}, "
          f"{steal['all_cpus']} % of all CPUs")

if __name__ == "__main__":
    sys.exit(main())
