"""Benchmark the servo loop in real time: the simulated procedure kept in compensation with the
servo loop in its own process at the robot's rate (hil/servo), measured by the loop itself.

Run: ``tools/bench loop [--seconds S] [--rate 125|500] [--no-rt] [--perception-process] [--json]``

Printed: what the OS granted the servo process (``rt_granted``), servo period p50/p99/max and its
jitter against the robot's period (8 ms CB3 / 2 ms e-Series), late periods (intervals > 2
periods; also over the windows in which the host's hypervisor took none of the loop's CPU, with
the host's steal, hil/soak/host.py), the longest interval, frame-to-command latency (exposure ->
the first servo command computed from that pair's setpoint) and, with ``--perception-process``
(the camera's own latency is measured there), beside its bound (camera p50 + locate p50 + one
servo period + 2 ms; p99 that + 10 ms: ``latency_bound_ms``, hil/soak/soak.py), operator stop ->
stop command, and RSS growth of both processes. ``--no-rt`` runs the same without asking for
real-time scheduling (the comparison). Wall-clock figures: they depend on the machine and on its
load (this is a shared 2-core machine). Definitions: hil/soak/soak.py and docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from hil.cli.cmd_soak import _latency_bound
from hil.config import default_setup_path
from hil.log import configure_logging
from hil.servo.rt import RtGranted
from hil.soak.soak import SoakResult, run_soak


def figures(res: SoakResult, seconds: float) -> dict[str, Any]:
    """The benchmark's JSON object from the soak's result."""
    period_ms = 1e3 / res.rate_hz
    return {
        "rate_hz": res.rate_hz,
        "period_ms": period_ms,
        "seconds": seconds,
        "compensate_s": res.compensate_s,
        "servo_commands": res.servo_commands,
        "servo_period_ms": res.period_ms,
        "jitter_ms": res.jitter_ms,
        "jitter_p99_over_period": (
            None
            if res.jitter_ms.get("p99") is None
            else round(float(res.jitter_ms["p99"] or 0.0) / period_ms, 4)
        ),
        "missed_deadlines": res.missed_deadlines,
        "missed_fraction": res.missed_fraction,
        "longest_gap_ms": res.longest_gap_ms,
        "host_steal_percent": res.host_steal_percent,
        "steal_free": res.steal_free,
        "frame_to_command_ms": res.frame_to_command_ms,
        "camera_latency_ms": res.camera_latency_ms,
        "locate_ms": res.locate_ms,
        "latency_bound_ms": res.latency_bound_ms,
        "stop_to_command_ms": res.stop_to_command_ms,
        "stale_periods": res.stale_periods,
        "rss_mb": res.rss_mb,
        "servo_rss_mb": res.servo_rss_mb,
        "rt_granted": res.rt_granted,
        "faults": res.faults,
        "final_state": res.final_state,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench loop", description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="seconds of compensation (default 60)")
    ap.add_argument("--rate", type=float, default=125.0, help="servo rate, Hz: 125 (CB3) or 500 (e-Series)")
    ap.add_argument("--config", help="simulated setup TOML (default: configs/sim.toml)")
    ap.add_argument("--no-rt", action="store_true", help="do not ask for real-time scheduling (comparison)")
    ap.add_argument("--perception-process", action="store_true",
                    help="grab, render and locate in the perception process (measures the camera's own "
                         "latency, so frame->command is shown beside its bound)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    configure_logging(level="error")
    with tempfile.TemporaryDirectory() as d:
        res = run_soak(
            args.seconds / 60.0,
            args.rate,
            config=Path(args.config) if args.config else default_setup_path(),
            plan=None,
            session_dir=Path(d),
            realtime=not args.no_rt,
            perception_process=args.perception_process,
        )
    period_ms = 1e3 / args.rate
    out = figures(res, args.seconds)
    if args.json:
        print(json.dumps(out))
        return 0
    j, p = res.jitter_ms, res.period_ms
    print(
        f"servo rate {args.rate:g} Hz (period {period_ms:.3f} ms), {res.compensate_s:.1f} s compensating, "
        f"{res.servo_commands} servo commands"
    )
    print(f"servo period p50/p99/max  {p.get('p50')} / {p.get('p99')} / {p.get('max')} ms")
    print(
        f"jitter p50/p99/max        {j.get('p50')} / {j.get('p99')} / {j.get('max')} ms "
        f"(p99 = {out['jitter_p99_over_period']} x period)"
    )
    print(
        f"missed deadlines          {res.missed_deadlines} ({100 * res.missed_fraction:.2f} % of intervals), "
        f"longest gap {res.longest_gap_ms} ms"
    )
    free = res.steal_free
    if free:
        print(f"  without host steal      {free['late']} of {free['intervals']} intervals "
              f"({100 * free['late_fraction']:.2f} %), {free['clean_windows']} of {free['windows']} "
              f"windows; host steal {res.host_steal_percent} %")
    f = res.frame_to_command_ms
    print(f"frame->command            {f.get('p50')} / {f.get('p99')} / {f.get('max')} ms (p50/p99/max)")
    print(f"latency bound             {_latency_bound(res)}")
    print(f"RSS supervisor / servo    {res.rss_mb} / {res.servo_rss_mb}")
    print(f"servo process             {RtGranted.from_dict(res.rt_granted).summary()}")
    if res.faults:
        print(f"faults                    {'; '.join(res.faults)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
