"""``tools/fakegv``: serve images (a PNG directory, rendered ring markers, or a live shared-memory
frame block) from fake GigE cameras.

Usage:
    tools/fakegv --images DIR [--address 127.0.0.1] [--serial GV01]
    tools/fakegv --images DIR --right-address 127.0.0.2          # stereo: DIR/left*.png, right*.png
    tools/fakegv --render --right-address 127.0.0.2 [--width 1920 --height 1080 --markers 8 --seed 1
                 --frames 4 --calibration-out cal.json --truth-out truth.json]
    tools/fakegv --shm NAME --right-address 127.0.0.2 [--control PATH] [--pair-window-ms 50]

``--shm NAME`` serves the newest pair of the shared-memory frame block NAME
(:mod:`hil.campaign.frameshm`; another process writes it, e.g. the simulated world's camera in a
``hil campaign --transport camera_stream_loss`` run): with a software trigger, frame n of the left
camera and frame n of the right camera are the same pair (whichever side fills frame n first takes
the snapshot; a camera that missed a trigger is put back in step: see
``emulators.fakegv.server.SharedPairSource``, window ``--pair-window-ms``). Before the first
pair is written the cameras send mid-grey frames.

Control interface (``--control PATH``): a Unix stream socket taking one command per line and
answering one line (``ok ...`` or ``error: ...``):

    stream_loss S     stop every fake camera (GVCP and GVSP go silent, clients lose control), start
                      them again on the same addresses after S seconds (0 < S <= 60); answers at once
    status            ``ok {json}``: running, frames served per camera, stream losses, torn reads,
                      times a camera that missed a trigger was put back in step
    help              the commands

The first line on stdout is JSON naming the cameras (``{"cameras": [{"side", "address",
"serial", "device_id"}...]}``); the process then serves until SIGINT/SIGTERM (or
``--duration-s``), then writes one JSON line per camera (frames filled) on stderr. A second
camera needs a second local address: run inside a private network namespace (``unshare -n``)
after ``ip link set lo up; ip addr add 127.0.0.2/8 dev lo``.
Errors: one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from emulators.control import serve_control_lines
from emulators.fakegv.server import FakeGvCamera, FakeGvError, SharedPairSource, U8Image
from hil.campaign.frameshm import FrameBlockError, FrameBlockReader


class UsageError(Exception):
    pass


def load_pngs(directory: Path, pattern: str) -> list[U8Image]:
    if not directory.is_dir():
        raise UsageError(f"{directory}: not a directory")
    files = sorted(directory.glob(pattern))
    if not files:
        raise UsageError(f"{directory}: no files match {pattern}")
    images = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise UsageError(f"{f}: not a readable image")
        images.append(np.asarray(img, dtype=np.uint8))
    return images


def render_images(args: argparse.Namespace) -> tuple[list[U8Image], list[U8Image], dict[str, Any]]:
    """Render ``args.frames`` stereo pairs of a random marker layout (hil.vision.render)."""
    from hil.vision.camera_model import StereoCalibration, save_calibration
    from hil.vision.render import RenderOptions, random_marker_layout, render_stereo

    scale = args.width / 1920.0
    cal = StereoCalibration.synthetic(f_px=1394.0 * scale, baseline_mm=args.baseline_mm,
                                      image_size=(args.width, args.height))
    rng = np.random.default_rng(args.seed)
    markers = random_marker_layout(rng, count=args.markers, distance_mm=args.distance_mm)
    lefts, rights = [], []
    truth: dict[str, Any] = {}
    for _ in range(args.frames):
        pair = render_stereo(cal, markers, RenderOptions(), rng)
        lefts.append(pair.left)
        rights.append(pair.right)
        truth = {"markers": [{"marker_id": t.marker_id, "center_mm": t.center_mm.tolist(),
                              "center_left_px": t.center_left_px.tolist(),
                              "center_right_px": t.center_right_px.tolist()} for t in pair.truth]}
    if args.calibration_out:
        save_calibration(cal, args.calibration_out)
    if args.truth_out:
        Path(args.truth_out).write_text(json.dumps(truth, indent=1))
    return lefts, rights, truth


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fakegv", description=__doc__.split("\n")[0] if __doc__ else None)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", type=Path, help="directory of PNGs (stereo: left*.png / right*.png)")
    src.add_argument("--render", action="store_true", help="render ring markers (hil.vision.render)")
    src.add_argument("--shm", default=None, metavar="NAME",
                     help="serve the newest pair of this shared-memory frame block (hil.campaign.frameshm)")
    p.add_argument("--pair-window-ms", type=float, default=50.0,
                   help="--shm: the two fills of one trigger are this close (less than the trigger "
                        "interval); used to put a camera that missed a trigger back in step")
    p.add_argument("--control", type=Path, default=None, metavar="PATH",
                   help="Unix socket for the control interface (stream_loss S, status, help)")
    p.add_argument("--address", default="127.0.0.1", help="left (or only) camera address")
    p.add_argument("--serial", default="GV01")
    p.add_argument("--right-address", default=None, help="serve a stereo pair: right camera address")
    p.add_argument("--right-serial", default="GV02")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--baseline-mm", type=float, default=120.0)
    p.add_argument("--distance-mm", type=float, default=1000.0)
    p.add_argument("--markers", type=int, default=8)
    p.add_argument("--frames", type=int, default=4, help="rendered pairs served in turn")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--calibration-out", type=Path, default=None)
    p.add_argument("--truth-out", type=Path, default=None)
    p.add_argument("--duration-s", type=float, default=None, help="stop after this long")
    return p


class Server:
    """The running fake cameras and their control interface (``stream_loss``, ``status``, ``help``)."""

    HELP = "commands: stream_loss S (stop the cameras, restart after S s), status, help"

    def __init__(self, cameras: list[tuple[str, FakeGvCamera]], source: SharedPairSource | None) -> None:
        self.cameras = cameras
        self.source = source
        self.lock = threading.Lock()
        self.stream_losses = 0
        self.restart_failures: list[str] = []
        self._restart: threading.Timer | None = None

    @property
    def running(self) -> bool:
        return all(cam.running for _, cam in self.cameras)

    def stream_loss(self, duration_s: float) -> None:
        """Stop every camera now; start them again after ``duration_s`` (a Timer thread)."""
        with self.lock:
            if self._restart is not None:
                raise ValueError("a stream loss is already in progress")
            for _, cam in self.cameras:
                cam.stop()
            if self.source is not None:
                self.source.reset()
            self.stream_losses += 1
            self._restart = threading.Timer(duration_s, self._start_again)
            self._restart.daemon = True
            self._restart.start()

    def _start_again(self) -> None:
        with self.lock:
            self._restart = None
            for side, cam in self.cameras:
                try:
                    cam.start()
                except FakeGvError as exc:
                    self.restart_failures.append(f"{side}: {exc}")
                    print(f"fakegv: restart failed: {side}: {exc}", file=sys.stderr, flush=True)

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "running": self.running, "stream_losses": self.stream_losses,
            "restart_failures": list(self.restart_failures),
            "frames_filled": {side: cam.frames_filled for side, cam in self.cameras},
        }
        if self.source is not None:
            out["frames_served"] = dict(self.source.served)
            out["grey_frames"] = self.source.grey
            out["realigned"] = self.source.realigned
            out["torn_reads"] = self.source.reader.torn_reads
        return out

    def command(self, line: str) -> str:
        """Execute one control line; the answer line."""
        verb, _, rest = line.strip().partition(" ")
        if verb == "stream_loss":
            try:
                duration_s = float(rest)
            except ValueError:
                return f"error: stream_loss needs a duration in seconds, got {rest.strip()!r}"
            if not (math.isfinite(duration_s) and 0.0 < duration_s <= 60.0):
                return f"error: stream_loss duration must be in (0, 60] s, got {duration_s}"
            try:
                self.stream_loss(duration_s)
            except ValueError as exc:
                return f"error: {exc}"
            return f"ok stream_loss {duration_s:g}"
        if verb == "status":
            with self.lock:
                return "ok " + json.dumps(self.status())
        if verb == "help":
            return "ok " + self.HELP
        return f"error: unknown command {verb!r} ({self.HELP})"

    def stop(self) -> None:
        with self.lock:
            if self._restart is not None:
                self._restart.cancel()
                self._restart = None
            for _, cam in self.cameras:
                cam.stop()


def serve_control(server: Server, path: Path, stop: threading.Event) -> socket.socket:
    """The control interface on the Unix socket ``path`` (a daemon thread)."""
    return serve_control_lines(path, server.command, stop, name="fakegv-control")


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    stereo = args.right_address is not None
    source: SharedPairSource | None = None
    try:
        if args.shm is not None:
            if not stereo:
                raise UsageError("--shm serves a stereo pair: give --right-address")
            if not 0.0 < args.pair_window_ms <= 1000.0:
                raise UsageError(f"--pair-window-ms must be in (0, 1000], got {args.pair_window_ms}")
            source = SharedPairSource(FrameBlockReader(args.shm), window_s=args.pair_window_ms / 1e3)
            lefts: list[U8Image] = []
            rights: list[U8Image] = []
        elif args.render:
            lefts, rights, _ = render_images(args)
            if not stereo:
                rights = []
        elif stereo:
            lefts, rights = load_pngs(args.images, "left*.png"), load_pngs(args.images, "right*.png")
            if len(lefts) != len(rights):
                raise UsageError(f"{args.images}: {len(lefts)} left*.png but {len(rights)} right*.png")
        else:
            lefts, rights = load_pngs(args.images, "*.png"), []
        cameras = [("left", FakeGvCamera(args.address, args.serial, lefts,
                                         source=None if source is None else source.side("left")))]
        if stereo:
            cameras.append(("right", FakeGvCamera(args.right_address, args.right_serial, rights,
                                                  source=None if source is None else source.side("right"))))
        for _, cam in cameras:
            cam.start()
    except (UsageError, FakeGvError, FrameBlockError) as exc:
        print(f"fakegv: {exc}", file=sys.stderr)
        return 2
    server = Server(cameras, source)
    stop = threading.Event()
    srv = serve_control(server, args.control, stop) if args.control is not None else None
    print(json.dumps({"cameras": [{"side": side, "address": cam.address, "serial": cam.serial,
                                   "device_id": cam.device_id} for side, cam in cameras]}), flush=True)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait(args.duration_s)
    for side, cam in cameras:
        print(json.dumps({"side": side, "frames_filled": cam.frames_filled}), file=sys.stderr, flush=True)
    server.stop()
    if srv is not None:
        srv.close()
        with contextlib.suppress(FileNotFoundError):
            args.control.unlink()
    if source is not None:
        source.reader.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
