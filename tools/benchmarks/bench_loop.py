"""Benchmark the control loop in real time: the simulated procedure kept in compensation while
servo targets stream at the robot's rate, measured at the robot driver boundary.

Run: ``tools/bench loop [--seconds S] [--rate 125|500] [--json]``

Printed: servo period p50/p99/max and its jitter against the robot's period (8 ms CB3 / 2 ms
e-Series), missed deadlines (intervals > 2 periods; on the wall clock the next stereo pair is
grabbed and located in the controller's prefetch thread while the stream goes on), the longest
gap, frame-to-command latency (exposure -> first servo command from that frame) against the
camera frame period, and RSS growth. Wall-clock figures: they depend on the machine and on its
load (this is a shared 2-core machine).
Definitions: hil/soak/soak.py and docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from hil.config import default_setup_path
from hil.log import configure_logging
from hil.soak.soak import run_soak


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench loop", description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="seconds of compensation (default 60)")
    ap.add_argument("--rate", type=float, default=125.0, help="servo rate, Hz: 125 (CB3) or 500 (e-Series)")
    ap.add_argument("--config", help="simulated setup TOML (default: configs/sim.toml)")
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
        )
    period_ms = 1e3 / args.rate
    out = {
        "rate_hz": args.rate,
        "period_ms": period_ms,
        "seconds": args.seconds,
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
        "frame_to_command_ms": res.frame_to_command_ms,
        "rss_mb": res.rss_mb,
        "faults": res.faults,
        "final_state": res.final_state,
    }
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
    f = res.frame_to_command_ms
    print(f"frame->command            {f.get('p50')} / {f.get('p99')} / {f.get('max')} ms (p50/p99/max)")
    print(f"RSS                       {res.rss_mb}")
    if res.faults:
        print(f"faults                    {'; '.join(res.faults)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
