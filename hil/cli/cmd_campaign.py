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

``--executor local|dask [--scheduler ADDRESS]``: where the runs execute (both tiers): this
machine's processes (default), or a Dask cluster (the scheduler at ADDRESS, or a LocalCluster of
``--jobs`` workers on loopback); needs the ``campaign-dask`` extra. ``--shard I/N`` (0-based) runs
the I-th of N deterministic slices of the matrix, for array jobs.

``--pairs``: compound faults instead (:mod:`hil.campaign.pairs`): every unordered pair of fault
kinds overlapping in every state (``A+B@STATE``, 455) and a second fault during the recovery from a
first (``A+B@STATE+recovery``, 168); SCENARIOS select them (``frame_drop+robot_disconnect@lock``,
``frame_drop`` = every pair with it, ``@lock``, ``+recovery``, wildcards); the table's rows are the
pairs; the JSON adds ``pairs`` and per run the second fault's ``second_*`` fields.

``hil campaign merge DIR... [--out DIR] [--json] [--allow-mismatch] [--allow-partial]``: combine
campaign outputs (shards) into one summary, the ``--json`` object of ``hil campaign``
(:mod:`hil.campaign.merge`). Every JSON object is documented in docs/campaign.md.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from hil.errors import InputFileError


class _CampaignParser(argparse.ArgumentParser):
    """``hil campaign``'s parser: ``hil campaign merge ...`` goes to the merge parser (the
    campaign's own positional SCENARIO list leaves no room for an argparse sub-command)."""

    merge_parser: argparse.ArgumentParser

    def parse_known_args(  # type: ignore[override]
        self, args: list[str] | None = None, namespace: argparse.Namespace | None = None,
    ) -> tuple[argparse.Namespace, list[str]]:
        if args and args[0] == "merge":
            return self.merge_parser.parse_known_args(args[1:], namespace)
        return super().parse_known_args(args, namespace)


def _add_merge_parser(prog: str) -> argparse.ArgumentParser:
    m = argparse.ArgumentParser(
        prog=f"{prog} merge",
        description="Combine campaign outputs (the --out directories of shards, or of any campaign "
        "runs of one matrix) into one report: DIR/campaign.json or transport.json and .html, and the "
        "failing runs' logs. Refuses outputs of different code versions, configs or matrices unless "
        "--allow-mismatch, missing shards unless --allow-partial, and always a run present twice. "
        "Exit code 0 when every merged run passed, 1 otherwise, 2 when refused.",
    )
    m.add_argument("dirs", nargs="+", metavar="DIR", help="campaign output directories")
    m.add_argument("--out", default="campaign-merged", help="output directory (default: ./campaign-merged)")
    m.add_argument("--json", action="store_true",
                   help="print the merged summary as one JSON object (the object of hil campaign --json)")
    m.add_argument("--allow-mismatch", action="store_true",
                   help="merge outputs of different code versions, config digests or matrices")
    m.add_argument("--allow-partial", action="store_true", help="merge although shards are missing")
    m.set_defaults(func=run_merge)
    return m


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "campaign",
        help="fault-injection campaign: every fault x workflow state x seeds on the simulator",
        description="Run fault kind x workflow state x seeds on the simulator (faster than real time, "
        "parallel processes) and check every run: no command outside the limits reached "
        "the robot driver, each fault ends in a safe state within a bounded time with the "
        "robot stopped, no unhandled exception or hang, a complete verifiable session log, "
        "and recovery continues to lock. Runs on this machine or on a Dask cluster (--executor); "
        "--shard runs a slice. 'hil campaign merge DIR...' combines outputs (see its --help).",
    )
    p.__class__ = _CampaignParser  # routes `hil campaign merge ...` (see _CampaignParser)
    assert isinstance(p, _CampaignParser)
    p.merge_parser = _add_merge_parser(p.prog)
    p.add_argument(
        "scenarios",
        nargs="*",
        metavar="SCENARIO",
        help="kind@state patterns (e.g. frame_drop@compensate, robot_disconnect, '@lock', "
        "'*@gate'); with --pairs A+B@STATE[+recovery] patterns; default: all",
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
    p.add_argument("--pairs", action="store_true",
                   help="compound faults: every pair of fault kinds overlapping in every state "
                        "(A+B@STATE: 91 pairs x 5 states) and a second fault during the recovery from a "
                        "first (A+B@STATE+recovery: 6 x 14 x register/compensate); SCENARIOS select them "
                        "(frame_drop+robot_disconnect@lock, frame_drop, '@lock', '+recovery', globs; "
                        "A+B matches either order); default: all 623")
    p.add_argument("--transport", action="store_true",
                   help="run the transport tier: faults through the emulators to the real drivers, "
                        "in real time (SCENARIOS: FAMILY@STATE transport scenario names)")
    p.add_argument("--executor", choices=["local", "dask"], default="local",
                   help="where runs execute: local processes (default) or a Dask cluster "
                        "(needs the campaign-dask extra)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="with --executor dask: the Dask scheduler (tcp://host:8786); default: a "
                        "LocalCluster of --jobs worker processes on 127.0.0.1")
    p.add_argument("--shard", metavar="I/N",
                   help="run only slice I of N of the matrix (0-based: 0/4 .. 3/4), for array jobs; "
                        "combine the outputs with 'hil campaign merge'")
    p.add_argument("--allow-mismatch", action="store_true",
                   help="let workers whose code version or config differs from this checkout run")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hil.campaign.campaign import run_campaign
    from hil.campaign.executor import open_executor
    from hil.campaign.pairs import select_pairs
    from hil.campaign.report import table
    from hil.campaign.scenarios import select
    from hil.campaign.shard import parse_shard
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
    if args.scheduler is not None and args.executor != "dask":
        raise InputFileError("--scheduler", "applies to --executor dask only")
    shard = parse_shard(args.shard) if args.shard is not None else None
    out = Path(args.out)

    def progress(msg: str) -> None:
        print(f"hil campaign: {msg}", file=sys.stderr, flush=True)

    if args.pairs and args.transport:
        raise InputFileError("--pairs", "does not apply to --transport (compound faults are simulator-tier)")
    if args.transport:
        if args.config or args.plan:
            raise InputFileError("--config/--plan",
                                 "do not apply to --transport (each run writes its own setup)")
        transport_scenarios = _transport_selection(list(args.scenarios), progress)
    else:
        scenarios: list[Any] = (select_pairs if args.pairs else select)(list(args.scenarios))
        config = Path(args.config) if args.config else default_setup_path()
        if not config.is_file():
            raise InputFileError(str(config), "no such setup file (--config)")
    with open_executor(args.executor, jobs=args.jobs, scheduler=args.scheduler) as executor:
        if args.transport:
            return _run_transport(args, transport_scenarios, seeds, out, progress, executor, shard)
        progress(f"{len(scenarios)} scenario(s) x {len(seeds)} seed(s) on {config}"
                 + (f", shard {shard}" if shard else ""))
        if args.pairs:
            return _run_pairs(args, scenarios, seeds, config, out, progress, executor, shard)
        summary = run_campaign(
            scenarios,
            seeds,
            config=config,
            plan=args.plan,
            out_dir=out,
            executor=executor,
            shard=shard,
            keep_logs=args.keep_logs,
            timeout_s=args.timeout if args.timeout is not None else 300.0,
            check_version=not args.allow_mismatch,
            progress=progress,
        )
    return _report(summary, args.json, table(summary["results"]), out, "campaign")


def _run_pairs(args: argparse.Namespace, scenarios: list[Any], seeds: list[int], config: Path, out: Path,
               progress: Any, executor: Any, shard: Any) -> int:
    from hil.campaign.pairs_campaign import run_pairs_campaign
    from hil.campaign.report import pair_row_of, row_order, table

    summary = run_pairs_campaign(
        scenarios, seeds, config=config, plan=args.plan, out_dir=out, executor=executor, shard=shard,
        keep_logs=args.keep_logs, timeout_s=args.timeout if args.timeout is not None else 300.0,
        check_version=not args.allow_mismatch, progress=progress)
    results = summary["results"]
    text = table(results, row_of=pair_row_of, order=row_order(results, pair_row_of))
    p = summary["pairs"]
    text += (f"pair scenarios: {p['runs']} ({p['overlapping']} overlapping, {p['recovery']} in recovery), "
             f"{p['passed']} passed\n")
    return _report(summary, args.json, text, out, "campaign")


def run_merge(args: argparse.Namespace) -> int:
    from hil.campaign.merge import merge_outputs
    from hil.campaign.outputs import stem_of
    from hil.campaign.report import table
    from hil.campaign.transport import transport_table

    out = Path(args.out)
    summary = merge_outputs([Path(d) for d in args.dirs], out_dir=out, allow_mismatch=args.allow_mismatch,
                            allow_partial=args.allow_partial)
    stem = stem_of(summary)
    text = transport_table(summary["results"]) if stem == "transport" else table(summary["results"])
    return _report(summary, args.json, text, out, stem)


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


def _transport_selection(patterns: list[str], progress: Any) -> list[Any]:
    from hil.campaign.transport import select_transport

    scenarios = select_transport(patterns)
    if not patterns:  # the whole matrix: leave out what cannot run on this machine, and say so
        from hil.campaign.gige import why_not_runnable

        why = why_not_runnable()
        if why is not None:
            scenarios = [s for s in scenarios if s.emulator != "fakegv"]
            progress(f"camera_stream_loss left out of the matrix: {why} (select it by name to see it fail)")
    return scenarios


def _run_transport(args: argparse.Namespace, scenarios: list[Any], seeds: list[int], out: Path,
                   progress: Any, executor: Any, shard: Any) -> int:
    from hil.campaign.transport import TRANSPORT_TIMEOUT_S, transport_table
    from hil.campaign.transport_tasks import run_transport_matrix

    progress(f"transport tier: {len(scenarios)} scenario(s) x {len(seeds)} seed(s), real time"
             + (f", shard {shard}" if shard else ""))
    summary = run_transport_matrix(
        scenarios, seeds, out_dir=out, executor=executor, shard=shard, keep_logs=args.keep_logs,
        timeout_s=args.timeout if args.timeout is not None else TRANSPORT_TIMEOUT_S,
        check_version=not args.allow_mismatch, progress=progress)
    return _report(summary, args.json, transport_table(summary["results"]), out, "transport")
