"""``hil probe CONFIG [--json] [--timeout-s S] [--window-s S]``: check each configured device
and say in plain words what was found (see docs/probe.md).

Exit 0 when every device passed (warnings allowed), 1 when a device failed, 2 when the setup file
is invalid. Human checklist on stdout by default; ``--json``: one JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil.config.loader import load_setup
from hil.errors import ConfigError
from hil.probe import DEFAULT_TIMEOUT_S, DEFAULT_WINDOW_S, EXIT_CONFIG_ERROR, probe_setup, render_text


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < value <= 600:
        raise argparse.ArgumentTypeError(f"{text} must be in (0, 600] seconds")
    return value


def run(args: argparse.Namespace) -> int:
    try:
        setup = load_setup(args.config)
    except ConfigError as exc:
        if not args.json:
            raise  # the CLI prints one line per problem, exit 2
        json.dump({"config": str(args.config), "status": "config_error", "exit_code": EXIT_CONFIG_ERROR,
                   "problems": [f"{exc.path}: {p}" for p in exc.problems]},
                  sys.stdout, indent=2)
        sys.stdout.write("\n")
        return EXIT_CONFIG_ERROR
    report = probe_setup(setup, config_name=str(args.config), timeout_s=args.timeout_s,
                         window_s=args.window_s)
    if args.json:
        json.dump(report.as_json(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(render_text(report))
    sys.stdout.flush()
    return report.exit_code


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "probe", help="check each configured device and say what was found",
        description="Check each device of a setup in turn (serial port, baud rate, tracker identity and "
                    "sensors; robot network ports, controller version, robot and safety mode; cameras, "
                    "resolution, frame rate, left/right skew) and say in plain words what was found. "
                    "Exit 0: all OK (warnings allowed); 1: a device failed; 2: the setup is invalid.")
    p.add_argument("config", help="setup TOML file")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the checklist")
    p.add_argument("--timeout-s", type=_positive, default=DEFAULT_TIMEOUT_S,
                   help=f"timeout of each check, s (default {DEFAULT_TIMEOUT_S:g}; opening a device adds "
                        "the waits its config asks for)")
    p.add_argument("--window-s", type=_positive, default=DEFAULT_WINDOW_S,
                   help="how long to watch each stream (frames, records, RTDE), s "
                        f"(default {DEFAULT_WINDOW_S:g})")
    p.set_defaults(func=run)
