"""Benchmark the CPU cost of one servo period: the servo loop (hil/servo/loop.py) stepping the
simulated arm of a setup while it tracks a target moving like a breathing patient, on a manual
clock - the same work the servo process does every period, without waiting between periods.

Run: ``tools/bench step [--rate 125|500] [--periods N] [--repeats R] [--config TOML] [--json]``

Printed: CPU time per period (``time.process_time``; median, min and max of R repeats of N periods)
and what share of the period that is at the chosen rate - the floor under the soak's
``servo_cpu_percent`` (the real loop also sleeps, spins and publishes). The work is deterministic;
the time is not (a shared machine: compare runs taken side by side). With the real UR driver the
period's cost is the RTDE exchange instead of the simulated arm's kinematics.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from hil.clock import ManualClock
from hil.config import build_devices, default_setup_path, load_setup
from hil.controller.assembly import rig_geometry
from hil.controller.compensation import limiter_args
from hil.log import configure_logging
from hil.servo.limiter import RateLimiter
from hil.servo.link import Regions
from hil.servo.loop import ServoLoop
from hil.servo.shm import Stat

#: The tracked target: a breathing-like excursion (mm) and its period (s), a new setpoint every
#: this many periods (a 30 Hz camera at 500 Hz is every ~16).
AMPLITUDE_MM = (5.0, 3.0, 1.0)
BREATH_PERIOD_S = 4.0
SETPOINT_EVERY = 16
WARMUP_PERIODS = 200


def measure(config: Path, rate_hz: float, periods: int, repeats: int) -> dict[str, Any]:
    """``per_period_s``: CPU seconds per period, one per repeat; ``commands``: servo commands the
    loop sent the arm (every period after the first setpoint, when the work is real).

    Raises:
        ValueError: a rate, period count or repeat count out of range.
    """
    if not (rate_hz > 0 and periods > 0 and repeats > 0):
        raise ValueError(f"rate, periods and repeats must be > 0 (got {rate_hz}, {periods}, {repeats})")
    setup = load_setup(config)
    clock = ManualClock(10**9)
    devices = build_devices(setup, clock)
    regions = Regions.create(shared=False)
    period_s = 1.0 / rate_hz
    try:
        devices.open_all()
        robot = devices.robot
        loop = ServoLoop(robot, robot.limits, clock, regions.block, regions.ring, regions.stats,
                         period_s=period_s, report=lambda kind, fields: None,
                         limiter=RateLimiter(*limiter_args(setup.procedure,
                                                           rig_geometry(setup, robot).T_tcp_from_guide)))
        home = robot.state_now().T_robot_from_tcp
        amplitude = np.asarray(AMPLITUDE_MM)

        def publish(k: int) -> None:
            now = clock.now_ns()
            phase = 2.0 * math.pi * k * period_s / BREATH_PERIOD_S
            regions.block.write_track(
                track_id=1, R=home.R, t_mm=home.t + amplitude * math.sin(phase),
                v_mm_s=amplitude * math.cos(phase) * 2.0 * math.pi / BREATH_PERIOD_S, w_rad_s=np.zeros(3),
                t_ref_ns=now, valid_until_ns=now + 10**9, exposure_t_ns=now, frame_seq=k, speed_scale=1.0,
                max_horizon_s=0.1, lead_s=0.0)

        def run(first: int, n: int) -> float:
            t0 = time.process_time()
            for k in range(first, first + n):
                if k % SETPOINT_EVERY == 0:
                    publish(k)
                loop.step(clock.now_ns())
                clock.advance(period_s)
            return time.process_time() - t0

        run(0, WARMUP_PERIODS)
        per_period = [run(WARMUP_PERIODS + r * periods, periods) / periods for r in range(repeats)]
        commands = int(regions.stats.get(Stat.COMMANDS))
    finally:
        regions.close()
        devices.close_all()
    return {"per_period_s": per_period, "commands": commands}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench step", description=__doc__.split("\n")[0])
    ap.add_argument("--rate", type=float, default=500.0, help="servo rate, Hz (default 500: e-Series)")
    ap.add_argument("--periods", type=int, default=2000, help="periods per repeat (default 2000)")
    ap.add_argument("--repeats", type=int, default=5, help="repeats (default 5)")
    ap.add_argument("--config", help="simulated setup TOML (default: configs/sim.toml)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    configure_logging(level="error")
    try:
        res = measure(Path(args.config) if args.config else default_setup_path(), args.rate, args.periods,
                      args.repeats)
    except ValueError as exc:
        print(f"tools/bench step: {exc}", file=sys.stderr)
        return 2
    us = [1e6 * s for s in res["per_period_s"]]
    period_us = 1e6 / args.rate
    med = statistics.median(us)
    out = {
        "rate_hz": args.rate,
        "period_us": round(period_us, 3),
        "periods": args.periods,
        "repeats": args.repeats,
        "cpu_per_period_us": {"median": round(med, 1), "min": round(min(us), 1), "max": round(max(us), 1)},
        "share_of_period": round(med / period_us, 4),
        "servo_commands": res["commands"],
    }
    if args.json:
        print(json.dumps(out))
        return 0
    if res["commands"] < args.periods * args.repeats:
        print(f"tools/bench step: the loop sent {res['commands']} commands in "
              f"{args.periods * args.repeats} periods (the arm refused the target?)", file=sys.stderr)
        return 1
    print(f"servo period at {args.rate:g} Hz ({period_us:.0f} us), {args.repeats} x {args.periods} periods: "
          f"CPU {med:.0f} us per period (median; min {min(us):.0f}, max {max(us):.0f}) = "
          f"{100 * med / period_us:.0f} % of the period")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
