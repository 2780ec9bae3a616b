"""``python -m emulators.ursim`` (with tools/ on PYTHONPATH) — what ``tools/ursim`` runs."""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys

from emulators.ursim.controller import ControllerVersion, UrController
from emulators.ursim.server import CONTROL_PORT, DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT, Emulator, Ports


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ursim",
        description="UR controller emulator for ur-rtde clients (RTDE, script port, dashboard) with a "
                    "line-based fault-control port. Runs until SIGINT/SIGTERM.")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--controller-version", default="3.15",
                   help="reported controller version: 3.15 (CB3, 125 Hz, default) or 5.11 (e-Series, 500 Hz)")
    p.add_argument("--model", choices=["ur3", "ur3e"], default=None,
                   help="arm kinematics (default: ur3 for 3.x, ur3e for 5.x)")
    p.add_argument("--control-port", type=int, default=CONTROL_PORT,
                   help=f"fault-control port (default {CONTROL_PORT})")
    p.add_argument("--verbose", action="store_true", help="print controller events on stderr")
    return p


async def _main(args: argparse.Namespace) -> int:
    try:
        version = ControllerVersion.parse(args.controller_version)
    except ValueError as exc:
        print(f"ursim: {exc}", file=sys.stderr)
        return 2
    if version.major not in (3, 5):
        print(f"ursim: controller version {version}: only 3.x (CB3) and 5.x (e-Series) are emulated",
              file=sys.stderr)
        return 2
    model = args.model or ("ur3" if version.is_cb3 else "ur3e")
    ctl = UrController(version, model)
    ports = Ports(RTDE_PORT, SCRIPT_PORT, DASHBOARD_PORT, args.control_port)
    sim = Emulator(ctl, args.host, ports, verbose=args.verbose)
    try:
        await sim.start()
    except OSError as exc:
        print(f"ursim: cannot listen on {args.host}: {exc}", file=sys.stderr)
        return 1
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, sim.request_stop)
    print(f"ursim ready host={args.host} rtde={ports.rtde} script={ports.script} "
          f"primary={ports.primary} secondary={ports.secondary} "
          f"dashboard={ports.dashboard} control={ports.control} version={version} model={model} "
          f"rate_hz={ctl.frequency_hz:g}", flush=True)
    await sim.run_until_stopped()
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return asyncio.run(_main(args))
    except KeyboardInterrupt:  # Ctrl-C before the signal handlers were installed
        return 130


if __name__ == "__main__":
    sys.exit(main())
