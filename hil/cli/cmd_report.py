"""``hil report SESSION_LOG [--out DIR]``: verify a session log and turn it into ``DIR/report.html``.

Stdout: one JSON object (report path, hash-chain verdict, numbers, plots, faults). Stderr:
progress lines. Exit codes: 0 report written and chain valid; 1 report written but the hash chain
is broken (the page says at which line); 2 the log cannot be read or is malformed (one line on
stderr naming the file and line), or matplotlib is not installed.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil.errors import HilError

EXIT_CHAIN_BROKEN = 1


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "report", help="verify a session log and write an HTML report with plots",
        description="Verify the session log's hash chain and write a self-contained HTML report "
                    "(state timeline, breathing and gate, guide and compensation errors, marker "
                    "residuals, robot speed, faults; numbers table). Exit 1 when the chain is broken.")
    p.add_argument("session_log", help="the session log (JSON lines) written by hil run / hil console")
    p.add_argument("--out", default=None,
                   help="output directory (default: <log dir>/<log name>_report)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        from hil.report import build_report
    except ImportError as exc:
        raise HilError("the report needs matplotlib "
                       f"(pip install 'needle-guide-hil[report]'): {exc}") from None

    def progress(msg: str) -> None:
        if not args.quiet:
            print(f"hil report: {msg}", file=sys.stderr, flush=True)

    result = build_report(args.session_log, args.out, progress)
    json.dump(result.to_dict(), sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0 if result.chain.ok else EXIT_CHAIN_BROKEN
