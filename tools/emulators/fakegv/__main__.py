"""``tools/fakegv``: serve images (a PNG directory, or rendered ring markers) from fake GigE cameras.

Usage:
    tools/fakegv --images DIR [--address 127.0.0.1] [--serial GV01]
    tools/fakegv --images DIR --right-address 127.0.0.2          # stereo: DIR/left*.png, right*.png
    tools/fakegv --render --right-address 127.0.0.2 [--width 1920 --height 1080 --markers 8 --seed 1
                 --frames 4 --calibration-out cal.json --truth-out truth.json]

The first line on stdout is JSON naming the cameras (``{"cameras": [{"side", "address",
"serial", "device_id"}...]}``); the process then serves until SIGINT/SIGTERM (or
``--duration-s``). A second camera needs a second local address: run inside a private network
namespace (``unshare -n``) after ``ip link set lo up; ip addr add 127.0.0.2/8 dev lo``.
Errors: one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from emulators.fakegv.server import FakeGvCamera, FakeGvError, U8Image


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


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    stereo = args.right_address is not None
    try:
        if args.render:
            lefts, rights, _ = render_images(args)
            if not stereo:
                rights = []
        elif stereo:
            lefts, rights = load_pngs(args.images, "left*.png"), load_pngs(args.images, "right*.png")
            if len(lefts) != len(rights):
                raise UsageError(f"{args.images}: {len(lefts)} left*.png but {len(rights)} right*.png")
        else:
            lefts, rights = load_pngs(args.images, "*.png"), []
        cameras = [("left", FakeGvCamera(args.address, args.serial, lefts))]
        if stereo:
            cameras.append(("right", FakeGvCamera(args.right_address, args.right_serial, rights)))
        for _, cam in cameras:
            cam.start()
    except (UsageError, FakeGvError) as exc:
        print(f"fakegv: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"cameras": [{"side": side, "address": cam.address, "serial": cam.serial,
                                   "device_id": cam.device_id} for side, cam in cameras]}), flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait(args.duration_s)
    for _, cam in cameras:
        print(json.dumps({"side": _, "frames_filled": cam.frames_filled}), file=sys.stderr, flush=True)
        cam.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
