"""``hil console [CONFIG]``: the operator console (terminal UI) over the procedure controller.

Same setup and plan resolution as ``hil run`` (default: the simulator and its plan). On exit,
prints one JSON object on stdout (final state, session log, faults). Exit code 0 when the
procedure reached DONE, 1 otherwise, 2 for a bad config/plan or a missing textual.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hil.errors import HilError, InputFileError
from hil.log import configure_logging


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "console", help="operator console (terminal UI) over the procedure controller",
        description="Step through a procedure with a terminal UI: workflow, markers, hold-breath gate, "
                    "robot, registration, faults; keys s/c/p/r/t/a/x/q. Without CONFIG: the simulator.")
    p.add_argument("config", nargs="?", help="setup TOML (default: the embedded configs/sim.toml)")
    p.add_argument("--plan", help="plan JSON (default: plans/<config name>_plan.json next to the config)")
    p.add_argument("--seed", type=int, help="override [simulation] seed")
    p.add_argument("--session-dir", default="sessions",
                   help="where the session log goes (default: sessions/)")
    p.add_argument("--fast", action="store_true",
                   help="simulated clock: run as fast as possible instead of pacing to the wall clock")
    p.add_argument("--igtl-port", type=int, default=None,
                   help="stream OpenIGTLink on 127.0.0.1:PORT (or the setup's [igtl] host)")
    p.add_argument("--viewer", metavar="FILE.rrd|ADDRESS", default=None,
                   help="stream the run live to Rerun: a .rrd file, or a viewer address such as "
                        "rerun+http://127.0.0.1:9876/proxy (docs/replay.md)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        from hil.console.app import ConsoleApp
        from hil.console.session import open_console_session
    except ImportError as exc:
        raise HilError("the console needs textual "
                       f"(pip install 'needle-guide-hil[console]'): {exc}") from None
    # While the UI owns the terminal, logs go to <session dir>/console.log (JSON lines).
    log_path = Path(args.session_dir) / "console.log"
    try:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        log_file = open(log_path, "a", encoding="utf-8")  # noqa: SIM115
    except OSError as exc:
        raise InputFileError(str(log_path), f"cannot write the console log: {exc.strerror or exc}") from None
    with log_file:
        configure_logging(json=True, level=getattr(args, "log_level", "info"), stream=log_file)
        try:
            session = open_console_session(args.config, plan=args.plan, session_dir=args.session_dir,
                                           seed=args.seed, fast=args.fast, igtl_port=args.igtl_port,
                                           viewer=args.viewer)
            try:
                ConsoleApp(session).run()
            finally:
                summary = session.close()
        finally:
            configure_logging(json=getattr(args, "log_json", False),
                              level=getattr(args, "log_level", "warning"))
    json.dump(summary, sys.stdout)
    sys.stdout.write("\n")
    print(f"hil console: session log {summary['session_log']} (hil report {summary['session_log']})",
          file=sys.stderr)
    return 0 if summary["final_state"] == "done" else 1
