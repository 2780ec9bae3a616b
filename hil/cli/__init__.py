"""The ``hil`` command line.

Each subcommand lives in its own module under :mod:`hil.cli` and exposes
``add_parser(subparsers) -> None``; the parser's ``func`` default takes the parsed arguments and
returns the exit code. Every :class:`hil.errors.HilError` (and driver error) a command raises
becomes one clear line on stderr and exit code 2 — never a traceback for a user mistake.

Ctrl-C (SIGINT) and SIGTERM (``kill``, a service manager stopping the console) end a command the
same way: the exception unwinds through the command's ``finally`` blocks, so the arm is stopped,
the servo process and every device are closed and the session log is closed; exit code 130
(interrupted) or 143 (terminated).
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType

from hil import __version__
from hil.errors import HilError
from hil.heap import use_one_arena
from hil.log import configure_logging

# Subcommand modules, in the order `hil --help` lists them. A module missing here is not a command.
COMMAND_MODULES: tuple[str, ...] = (
    "hil.cli.cmd_register",
    "hil.cli.cmd_states",
    "hil.cli.cmd_run",
    "hil.cli.cmd_campaign",
    "hil.cli.cmd_soak",
    "hil.cli.cmd_drivers",
    "hil.cli.cmd_check_config",
    "hil.cli.cmd_tracker_calibrate",
    "hil.cli.cmd_rig_calibrate",
    "hil.cli.cmd_calibrate",
    "hil.cli.cmd_locate",
    "hil.cli.cmd_report",
    "hil.cli.cmd_replay",
    "hil.cli.cmd_console",
    "hil.cli.cmd_probe",
    "hil.cli.cmd_stereotaxy",
    "hil.cli.cmd_traces",
)

class TerminatedError(KeyboardInterrupt):
    """SIGTERM: unwinds like Ctrl-C (module doc)."""


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    raise TerminatedError()


EXIT_USAGE = 2
EXIT_ERROR = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hil",
        description="Hardware-in-the-loop controller for an image-guided needle-puncture robot.",
    )
    parser.add_argument("--version", action="version", version=f"hil {__version__}")
    parser.add_argument("--log-json", action="store_true", help="log JSON lines on stderr")
    parser.add_argument(
        "--log-level", default="warning", choices=["debug", "info", "warning", "error"],
        help="minimum log level on stderr (default: warning)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``hil`` console script. Returns the process exit code. SIGTERM is
    handled like Ctrl-C while the command runs (module doc); the previous handler is restored.
    First, before any thread starts, every thread is put on one malloc arena (hil/heap.py: the
    supervisor's freed image buffers must stay trimmable)."""
    use_one_arena()
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(json=args.log_json, level=args.log_level)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if in_main else None
    try:
        code: int = args.func(args)
    except HilError as exc:
        for line in str(exc).splitlines() or [type(exc).__name__]:
            print(f"hil {args.command}: error: {line}", file=sys.stderr)
        return EXIT_ERROR
    except TerminatedError:
        print(f"hil {args.command}: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"hil {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)
    return code

if __name__ == "__main__":
    sys.exit(main())
