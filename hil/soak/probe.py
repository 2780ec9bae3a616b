"""Probe what this machine grants a real-time loop, without the project's code in the loop: a fixed
piece of work every period, with the servo process's own real-time set-up (SCHED_FIFO, the loop's
CPU, memory locked, the garbage collector frozen; :mod:`hil.servo.rt`) and its sleep-then-spin wait.

Run: ``tools/bench host [--seconds S] [--rate HZ] [--work-ms MS] [--json]`` or ``python -m
hil.soak.probe ...``; ``hil soak --probe-host S`` runs it for S seconds before and after the soak
(:func:`probe_in_subprocess`).

The work (numpy and Python arithmetic like a servo step's, sized at start to ``--work-ms`` of CPU)
is the same every period, so any period it takes longer is the machine's doing: on a virtual
machine the host runs other guests on the CPU behind ours (*steal*), and a SCHED_FIFO thread
inside the guest cannot prevent it. The figures, per period: the work's wall time and its CPU time
(``CLOCK_THREAD_CPUTIME_ID``, which on a guest with steal accounting leaves out what the host
took), how many periods the work took over twice its median and over a whole period, wake-ups
more than a period late, intervals over two periods (the soak's *late*), and the steal of the CPU
over the run (``/proc/stat``). Read ``hil soak`` figures beside it: a late share the probe shows
too is the machine's; what the soak adds on top is ours. Needs Linux; without root it runs
unprivileged and says so (``rt_granted``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
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
        c1 = time.thread_time_ns()   # the CPU interval inside the wall one (hil/servo/process.py)
        done = time.monotonic_ns()
        wall[k], cpu[k], wake[k], starts[k] = done - now, c1 - c0, now - next_ns, now
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


def run_probe(seconds: float, rate_hz: float, work_ms: float) -> dict[str, Any]:
    """Take the servo process's real-time set-up in this process (for good: run it in a process of
    its own), size the work and probe for ``seconds``; the figures with ``rate_hz``, ``work_ms``,
    ``work_units``, ``rt_granted``, ``cpu`` and ``host_steal_percent`` (``loop_cpu``,
    ``all_cpus``; None where ``/proc/stat`` has none). Blocks for about ``seconds``.

    Raises:
        ValueError: seconds or rate not > 0, or work not within (0, the period).
    """
    if not (seconds > 0 and rate_hz > 0 and 0 < work_ms < 1e3 / rate_hz):
        raise ValueError(f"need seconds > 0, rate > 0 and 0 < work-ms < the period "
                         f"(got {seconds}, {rate_hz}, {work_ms})")
    cpu = default_cpu()
    granted = apply_realtime(PRIORITY, cpu)
    units = size_work(work_ms)
    s0, a0 = sample_steal(cpu), sample_steal(None)
    out = probe(seconds, rate_hz, units)
    s1, a1 = sample_steal(cpu), sample_steal(None)
    out.update({"rate_hz": rate_hz, "work_ms": work_ms, "seconds": seconds, "work_units": units,
                "rt_granted": granted.to_dict(), "rt_summary": granted.summary(), "cpu": cpu,
                "host_steal_percent": {
                    "loop_cpu": steal_percent(s0, s1) if s0 and s1 else None,
                    "all_cpus": steal_percent(a0, a1, os.cpu_count() or 1) if a0 and a1 else None}})
    return out


def per_10k(out: dict[str, Any]) -> float:
    """Late intervals per 10,000 of a probe's figures."""
    return 1e4 * float(out["late"]) / max(int(out["intervals"]), 1)


def format_lines(out: dict[str, Any]) -> list[str]:
    """The probe's figures as text lines (``tools/bench host``)."""
    w, c = out["work_wall_ms"], out["work_cpu_ms"]
    n, steal = out["periods"], out["host_steal_percent"]
    return [
        f"host probe: {out['work_ms']:g} ms of fixed work every {1e3 / out['rate_hz']:g} ms on CPU "
        f"{out['cpu']} for {out['seconds']:g} s ({out['rt_summary']})",
        f"work wall p50/p99/max  {w['p50']} / {w['p99']} / {w['max']} ms "
        f"(its CPU time p50/max {c['p50']} / {c['max']} ms)",
        f"stretched              {out['stretched_over_2x']} of {n} periods over twice the median "
        f"({100 * out['stretched_over_2x'] / n:.2f} %), {out['work_over_a_period']} over a period",
        f"woke late              {out['woke_late']} over a period late, "
        f"longest {out['longest_wake_delay_ms']} ms",
        f"late intervals         {out['late']} of {out['intervals']} over two periods "
        f"({per_10k(out):.1f} in 10,000), longest {out['longest_interval_ms']} ms",
        f"host steal             {steal['loop_cpu']} % of CPU {out['cpu']}, "
        f"{steal['all_cpus']} % of all CPUs",
    ]


def probe_in_subprocess(seconds: float, rate_hz: float, work_ms: float = 0.5) -> dict[str, Any]:
    """Run the probe in a process of its own (``python -m hil.soak.probe --json``), blocking for
    about ``seconds``; the process is waited for or killed on every path.

    Raises:
        RuntimeError: the probe failed or did not finish within ``seconds`` + 60 s (its message).
    """
    cmd = [sys.executable, "-m", "hil.soak.probe", "--json", "--seconds", repr(seconds),
           "--rate", repr(rate_hz), "--work-ms", repr(work_ms)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 60.0, check=False)
    except subprocess.TimeoutExpired as exc:   # subprocess.run killed it
        raise RuntimeError(f"host probe did not finish within {seconds + 60.0:g} s") from exc
    if proc.returncode != 0:
        why = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit code {proc.returncode}"
        raise RuntimeError(f"host probe failed: {why}")
    result: dict[str, Any] = json.loads(proc.stdout)
    return result


def main(argv: list[str] | None = None, prog: str = "python -m hil.soak.probe") -> int:
    """The command line (module doc). Exit code 0, or 2 for a bad argument."""
    ap = argparse.ArgumentParser(prog=prog, description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="how long to probe, s (default 30)")
    ap.add_argument("--rate", type=float, default=500.0, help="periods per second, Hz (default 500)")
    ap.add_argument("--work-ms", type=float, default=0.5,
                    help="CPU time of the fixed work per period, ms (default 0.5: a simulated servo step)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    try:
        out = run_probe(args.seconds, args.rate, args.work_ms)
    except ValueError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(out) if args.json else "\n".join(format_lines(out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
