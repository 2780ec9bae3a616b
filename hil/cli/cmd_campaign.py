"""``hil campaign [SCENARIOS...] [--seeds N] [--jobs J] [--out DIR] [--json]``: fault-injection
campaign on the simulator (docs/campaign.md).

Runs every selected scenario (fault kind x workflow state, e.g. ``frame_drop@compensate``;
``frame_drop`` = all states, ``@lock`` = all kinds, shell wildcards allowed; none = the whole
matrix) for each seed, in parallel processes, faster than real time. Stdout: the summary table,
or with ``--json`` one object (``runs``, ``passed``, ``failed``, ``worst_safe_latency_ms``,
``failing`` with replay commands, ``results``). Stderr: progress. Files: ``DIR/campaign.json``,
``DIR/campaign.html`` and the session logs of failing runs in ``DIR/logs``. Exit code 0 when
every run passed, 1 otherwise.

``--transport``: the transport tier instead (:mod:`hil.campaign.transport`): faults sent through
the emulators' fault channels to the REAL drivers (``ur_rtde`` on ``tools/ursim``, ``fob`` on
``tools/trackersim``), in real time (``--jobs`` 1 by default); SCENARIOS are transport scenario
names FAMILY@STATE (``rtde_protective_stop@compensate``, ``serial``, ``@lock``, ...; none = every
family x every state); stdout: the family x state table; files ``DIR/transport.json`` and
``DIR/transport.html``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from hil.errors import InputFileError


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "campaign",
        help="fault-injection campaign: every fault x workflow state x seeds on the simulator",
        description="Run fault kind x workflow state x seeds on the simulator (faster than real time, "
        "parallel processes) and check every run: no command outside the limits reached "
        "the robot driver, each fault ends in a safe state within a bounded time with the "
        "robot stopped, no unhandled exception or hang, a complete verifiable session log, "
        "and recovery continues to lock.",
    )
    p.add_argument(
        "scenarios",
        nargs="*",
        metavar="SCENARIO",
        help="kind@state patterns (e.g. frame_drop@compensate, robot_disconnect, '@lock', "
        "'*@gate'); default: all",
    )
    p.add_argument("--seeds", type=int, default=1, help="number of seeds (1..N; default 1)")
    p.add_argument(
        "--seed",
        type=int,
        action="append",
        dest="seed_list",
        help="run exactly this seed (repeatable; replaces --seeds) -- for replaying a failure",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="parallel processes (default: CPU count, at most 4; with --transport 1, as each run is "
             "real time)",
    )
    p.add_argument("--out", default="campaign", help="output directory (default: ./campaign)")
    p.add_argument("--config", help="simulated setup TOML (default: the embedded configs/sim.toml)")
    p.add_argument("--plan", help="plan JSON (default: plans/<config name>_plan.json next to the config)")
    p.add_argument("--keep-logs", action="store_true", help="keep the session logs of passing runs too")
    p.add_argument("--timeout", type=float, default=None,
                   help="wall-time bound of one run, s (default 300; 150 with --transport)")
    p.add_argument("--transport", action="store_true",
                   help="run the transport tier: faults through the emulators to the real drivers, "
                        "in real time (SCENARIOS: FAMILY@STATE transport scenario names)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hil.campaign.campaign import run_campaign
    from hil.campaign.report import table
    from hil.campaign.scenarios import select
    from hil.config import default_setup_path

    if args.seed_list:
        seeds = sorted(set(args.seed_list))
    else:
        if args.seeds < 1:
            raise InputFileError("--seeds", f"must be >= 1, got {args.seeds}")
        seeds = list(range(1, args.seeds + 1))
    if any(s < 0 for s in seeds):
        raise InputFileError("--seed", f"must be >= 0, got {min(seeds)}")
    if args.jobs is None:
        args.jobs = 1 if args.transport else max(1, min(os.cpu_count() or 1, 4))
    if args.jobs < 1:
        raise InputFileError("--jobs", f"must be >= 1, got {args.jobs}")
    if args.timeout is not None and args.timeout <= 0:
        raise InputFileError("--timeout", f"must be > 0, got {args.timeout}")
    out = Path(args.out)

    def progress(msg: str) -> None:
        print(f"hil campaign: {msg}", file=sys.stderr, flush=True)

    if args.transport:
        return _run_transport(args, seeds, out, progress)
    scenarios = select(list(args.scenarios))
    config = Path(args.config) if args.config else default_setup_path()

    progress(f"{len(scenarios)} scenario(s) x {len(seeds)} seed(s) on {config}")
    summary = run_campaign(
        scenarios,
        seeds,
        config=config,
        plan=args.plan,
        jobs=args.jobs,
        out_dir=out,
        keep_logs=args.keep_logs,
        timeout_s=args.timeout if args.timeout is not None else 300.0,
        progress=progress,
    )
    return _report(summary, args.json, table(summary["results"]), out, "campaign")


def _report(summary: dict[str, Any], as_json: bool, table_text: str, out: Path, stem: str) -> int:
    """Print the summary (one JSON object, or the table, the counts and the failing runs with
    their replay commands) and return the exit code: 0 when every run passed, else 1."""
    if as_json:
        sys.stdout.write(json.dumps(summary, default=str) + "\n")
    else:
        sys.stdout.write(table_text)
        sys.stdout.write(
            f"{summary['runs']} runs: {summary['passed']} passed, {summary['failed']} failed; "
            f"worst safe-state latency {summary['worst_safe_latency_ms']} ms\n"
        )
        for f in summary["failing"]:
            sys.stdout.write(
                f"FAIL {f['scenario']} seed {f['seed']}: {'; '.join(f['reasons'])}\n"
                f"     replay: {f['replay']}\n"
            )
        sys.stdout.write(f"wrote {out / (stem + '.json')} and {out / (stem + '.html')}\n")
    return 0 if summary["failed"] == 0 else 1


def _run_transport(args: argparse.Namespace, seeds: list[int], out: Path, progress: Any) -> int:
    from hil.campaign.transport import (
        TRANSPORT_TIMEOUT_S,
        run_transport_campaign,
        select_transport,
        transport_table,
    )

    if args.config or args.plan:
        raise InputFileError("--config/--plan", "do not apply to --transport (each run writes its own setup)")
    scenarios = select_transport(list(args.scenarios))
    if not args.scenarios:  # the whole matrix: leave out what cannot run on this machine, and say so
        from hil.campaign.gige import why_not_runnable

        why = why_not_runnable()
        if why is not None:
            scenarios = [s for s in scenarios if s.emulator != "fakegv"]
            progress(f"camera_stream_loss left out of the matrix: {why} (select it by name to see it fail)")
    progress(f"transport tier: {len(scenarios)} scenario(s) x {len(seeds)} seed(s), {args.jobs} at a time, "
             "real time")
    summary = run_transport_campaign(
        scenarios, seeds, out_dir=out, keep_logs=args.keep_logs, jobs=args.jobs,
        timeout_s=args.timeout if args.timeout is not None else TRANSPORT_TIMEOUT_S, progress=progress)
    return _report(summary, args.json, transport_table(summary["results"]), out, "transport")
