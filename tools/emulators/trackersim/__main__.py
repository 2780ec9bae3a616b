"""``tools/trackersim``: run a Flock of Birds or Aurora emulator on a pseudo-terminal.

The FIRST line of stdout is the serial device path to open (``/dev/pts/N``); the emulator runs
until SIGINT or SIGTERM. Progress and errors go to stderr.

Control interface (``--control PATH``): a Unix stream socket taking one command per line and
answering one line (``ok ...`` or ``error: ...``):

    fault SPEC        arm a fault (syntax in emulators.trackersim.faults, e.g. ``fault garbage,count=3``)
    clear [KIND]      disarm one kind, or all faults
    reset             power cycle the device, silently (a pty has no RTS line to do it); the
                      Aurora's ``fault reset`` is a reset that also sends RESET, as a device does
    status            one JSON object: protocol, baud, host_baud, faults fired, device state

Several commands may share a line, separated by ``;`` (run in order under the device lock, so
nothing happens between them; the answer is the first error, or ``ok``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from emulators.control import serve_control_lines
from emulators.trackersim.aurora_device import AuroraDevice
from emulators.trackersim.device import EmulatedDevice
from emulators.trackersim.faults import Faults, parse_fault
from emulators.trackersim.fob_device import FobDevice
from emulators.trackersim.poses import BreathingPoses, PoseSource, StaticPoses, load_pose_script
from emulators.trackersim.pty_link import PtyLink
from hil.errors import HilError
from hil.log import configure_logging

EPILOG = """\
fault SPEC (--fault, or the control interface's "fault SPEC"):
  KIND[,count=N][,p=P][,seconds=S][,after=S][,bytes=N][,mask=M][,baud=B][,handles=H+H][,seed=K]
  garbage        random bytes inserted into a record/reply (bytes=N, mask=0x7f)
  truncate       the tail of a record/reply dropped
  lost_phase     (fob) the phasing bit of a record cleared
  bad_crc        (aurora) the CRC of a reply wrong (ASCII: last digit; BX: body CRC)
  silence        nothing sent, for seconds=S or until cleared
  wrong_baud     the device runs at baud=B (fob: its dip switches; aurora: instead of the COMM rate)
  tool_missing   (aurora) tools on handles=0A+0B (default all) MISSING, for seconds=S or until cleared
  out_of_volume  (aurora) tools on handles out of volume (port status 0x40; MISSING without
                 reply option 0x0800), for seconds=S or until cleared
  reset          (aurora) the device resets mid-session: RESET sent at 9600, back at 9600 baud,
                 not initialised, not tracking
  comm_baud      (aurora) the next COMM (count=N: the next N) answered OKAY, but the device
                 then runs at baud=B instead of the rate asked
  count=N: the next N records/replies; p=P: each with probability P; after=S: armed S s later.

control interface (--control PATH; one line in, one line out: "ok ..." or "error: ..."):
  fault SPEC | clear [KIND] | reset (silent power cycle) | status (JSON); several on one line
  separated by ";" (run together, under the device lock), e.g.
  echo 'fault comm_baud,baud=57600; fault reset' | socat - UNIX-CONNECT:/tmp/aurora.sock
  or echo 'fault tool_missing,handles=0A,seconds=1' | socat - UNIX-CONNECT:/tmp/aurora.sock
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="trackersim", description=__doc__.split("\n\n")[0], epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--protocol", choices=["fob", "aurora"], required=True)
    p.add_argument("--baud", type=int, default=115200,
                   help="fob: the baud rate set by the Bird's dip switches (default 115200); "
                        "the Aurora always starts at 9600 and follows COMM")
    p.add_argument("--birds", type=int, default=1,
                   help="fob: 1 = standalone bird at address 0; N>1 = flock on FBB addresses 1..N")
    p.add_argument("--rate-hz", type=float, default=100.0, help="fob: measurement rate (default 100)")
    p.add_argument("--tools", type=int, default=2, help="aurora: wired tools on handles 0A, 0B, ...")
    p.add_argument("--frame-rate-hz", type=float, default=40.0, help="aurora: frame counter rate")
    p.add_argument("--motion", choices=["static", "breathing"], default="breathing")
    p.add_argument("--amplitude-mm", type=float, default=8.0, help="breathing amplitude along z")
    p.add_argument("--period-s", type=float, default=4.0, help="breathing period")
    p.add_argument("--poses", type=Path, help="pose script (JSON or CSV); replaces the static base poses")
    p.add_argument("--world", type=Path,
                   help='setup TOML with [tracker] driver = "sim": report the poses of its sensors '
                        "in the simulated world")
    p.add_argument("--world-sensor", action="append", default=[], metavar="ID=NAME",
                   help="map a device id (FBB address / port handle) to a sim sensor (default: in order)")
    p.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help="arm a fault at start, e.g. garbage,p=0.05 or silence,after=2,seconds=1 (repeatable)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the fault injector")
    p.add_argument("--control", type=Path, help="Unix socket path for the control interface")
    p.add_argument("--link", type=Path, help="also make a symlink at this path to the pty")
    return p


def make_device(args: argparse.Namespace, link: PtyLink, faults: Faults) -> EmulatedDevice:
    if args.protocol == "fob":
        order = tuple(str(a) for a in ([0] if args.birds == 1 else range(1, args.birds + 1)))
        base: PoseSource = StaticPoses(order=order)
    else:
        order = tuple(f"{0x0A + i:02X}" for i in range(args.tools))
        base = StaticPoses(order=order, default_mm=(0.0, 0.0, -250.0), spacing_mm=(40.0, 0.0, 0.0))
    if args.poses is not None:
        base = load_pose_script(args.poses)
    if args.world is not None:
        from emulators.trackersim.world_poses import WorldPoses

        mapping = dict(item.split("=", 1) for item in args.world_sensor) if args.world_sensor else None
        base = WorldPoses(args.world, order, mapping)
        args.motion = "static"  # the world breathes by itself
    poses: PoseSource = base
    if args.motion == "breathing":
        poses = BreathingPoses(base, amplitude_mm=(0.0, 0.0, args.amplitude_mm), period_s=args.period_s)
    if args.protocol == "fob":
        return FobDevice(link, poses, faults, baud=args.baud, n_birds=args.birds, rate_hz=args.rate_hz)
    return AuroraDevice(link, poses, faults, n_tools=args.tools, frame_rate_hz=args.frame_rate_hz)


def control_command(device: EmulatedDevice, line: str) -> str:
    """Execute one control-interface line (one command, or several separated by ``;``); returns
    the answer line: the first error, else the last answer."""
    answer = "ok"
    for part in line.split(";"):
        answer = _one_command(device, part)
        if not answer.startswith("ok"):
            return answer
    return answer


def _one_command(device: EmulatedDevice, line: str) -> str:
    verb, _, rest = line.strip().partition(" ")
    try:
        if verb == "fault":
            device.faults.inject(parse_fault(rest), device.now_s())
            return "ok"
        if verb == "clear":
            device.faults.clear(rest.strip() or None)
            return "ok"
        if verb == "reset":
            device.reset()
            return "ok"
        if verb == "status":
            return "ok " + json.dumps(status(device))
    except ValueError as exc:
        return f"error: {exc}"
    return f"error: unknown command {verb!r} (fault, clear, reset, status)"


def status(device: EmulatedDevice) -> dict[str, Any]:
    out: dict[str, Any] = {"path": device.link.path, "baud": device.device_baud(),
                           "host_baud": device.link.host_baud(), "faults_fired": dict(device.faults.fired)}
    if isinstance(device, FobDevice):
        out.update(protocol="fob", stream=device.stream, group_mode=device.group_mode,
                   error_code=device.error_code)
    elif isinstance(device, AuroraDevice):
        out.update(protocol="aurora", initialized=device.initialized, tracking=device.tracking,
                   frame=device.frame_number())
    return out


def serve_control(device: EmulatedDevice, path: Path, stop: threading.Event) -> socket.socket:
    def answer(line: str) -> str:
        with device.lock:
            return control_command(device, line)

    return serve_control_lines(path, answer, stop, name="trackersim-control")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(level="warning")  # logs to stderr: stdout's first line is the device path
    faults = Faults(seed=args.seed)
    try:
        for spec in args.fault:
            faults.inject(parse_fault(spec))
        link = PtyLink()
        device = make_device(args, link, faults)
    except (ValueError, HilError) as exc:
        print(f"trackersim: error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    if args.link is not None:
        with contextlib.suppress(FileNotFoundError):
            args.link.unlink()
        os.symlink(link.path, args.link)
    srv = serve_control(device, args.control, stop) if args.control is not None else None
    print(link.path, flush=True)
    print(f"trackersim: {args.protocol} emulator on {link.path}", file=sys.stderr, flush=True)

    def on_signal(signum: int, frame: object) -> None:
        stop.set()
        device.stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    device.start()
    while not stop.is_set():
        stop.wait(0.5)
    device.stop()
    if srv is not None:
        srv.close()
        with contextlib.suppress(FileNotFoundError):
            args.control.unlink()
    if args.link is not None:
        with contextlib.suppress(FileNotFoundError):
            args.link.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
