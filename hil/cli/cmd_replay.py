"""``hil replay SESSION.jsonl [--out FILE.rrd] [--serve] [--allow-unverified] [--json]``: the
session as one Rerun recording (3D scene, time series, transitions) on the session's clock.

Stdout: ``--json`` one JSON object (``path``, ``bytes``, ``entities``, ``timelines``, ``records``,
``verified``, ``reason``, and ``url`` with ``--serve``); else a few lines. Exit codes: 0 written;
2 the log is refused (missing, unreadable, tampered, truncated, another version: one line naming
the file and what is wrong) or rerun-sdk is missing. ``--serve`` then serves the web viewer on
127.0.0.1, prints its address and blocks until Ctrl-C (exit 130). docs/replay.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

#: Said on stderr with --serve (docs/replay.md, "The served web viewer reaches only loopback").
WEB_VIEWER_NOTE = ("hil replay: note: the page may reach only 127.0.0.1 (a Content-Security-Policy and "
                   "a guard refuse the web viewer's analytics, web font, release check and examples "
                   "in the browser); open only the address above")


def port_number(text: str) -> int:
    """A TCP port 0..65535 (argparse type)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= n <= 65535:
        raise argparse.ArgumentTypeError(f"port out of range 0..65535: {n}")
    return n


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "replay", help="3D replay of a session log in the Rerun viewer (.rrd)",
        description="Verify a session log's hash chain and write it as one Rerun recording on the "
                    "session's own clock: markers, robot TCP and guide axis, plan, transitions, "
                    "following error, latency, gate deviation, servo figures. Open it with "
                    "`rerun FILE.rrd` or --serve.")
    p.add_argument("session_log", help="the session log (JSON lines) written by hil run / hil console")
    p.add_argument("--out", default=None, help="the .rrd to write (default: <log>.rrd beside the log)")
    p.add_argument("--serve", action="store_true",
                   help="then serve the web viewer on 127.0.0.1, print its address, block until Ctrl-C")
    p.add_argument("--web-port", type=port_number, default=9090,
                   help="web viewer port with --serve (default 9090; 0: a free port)")
    p.add_argument("--grpc-port", type=port_number, default=9876,
                   help="recording (gRPC) port with --serve (default 9876; 0: a free port)")
    p.add_argument("--allow-unverified", action="store_true",
                   help="replay a log whose hash chain is broken or incomplete, marked UNVERIFIED")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hil.replay import write_replay
    from hil.replay.serve import ViewerServer

    result = write_replay(args.session_log, args.out, allow_unverified=args.allow_unverified)
    doc = result.to_dict()
    server = ViewerServer(result.path, args.web_port, args.grpc_port).start() if args.serve else None
    try:
        if server is not None:
            doc["url"] = server.url
        if args.json:
            sys.stdout.write(json.dumps(doc) + "\n")
        else:
            mark = "" if result.verified else f" (UNVERIFIED: {result.reason})"
            sys.stdout.write(f"recording {result.path} ({result.bytes} bytes, {len(result.entities)} "
                             f"entities){mark}\nopen it   rerun {result.path}\n")
            if server is not None:
                sys.stdout.write(f"serving   {server.url}  (Ctrl-C to stop)\n")
        sys.stdout.flush()
        if server is not None:
            print(WEB_VIEWER_NOTE, file=sys.stderr, flush=True)
        if server is not None:
            server.wait()
    finally:
        if server is not None:
            server.close()
    return 0
