"""Record the stereo camera of a setup: ``python -m drivers.camera.record SETUP OUT --pairs N``.

Builds the setup's devices (none is opened but the camera), grabs ``--pairs`` pairs and writes a
recording (:mod:`drivers.camera.recording`) that a ``driver = "replay"`` camera plays back.
Prints one JSON line with the result on stdout; errors are one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from drivers.camera.recording import record
from hil.config.build import build_devices, clock_for
from hil.config.loader import load_setup
from hil.errors import HilError


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivers.camera.record", description=__doc__)
    p.add_argument("setup", type=Path, help="setup TOML whose [camera] is recorded")
    p.add_argument("out", type=Path, help="new recording directory")
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--codec", choices=("ffv1", "png"), default="ffv1")
    p.add_argument("--timeout-s", type=float, default=2.0, help="per-pair grab timeout")
    args = p.parse_args(argv)
    if args.pairs <= 0:
        p.error("--pairs must be > 0")
    try:
        setup = load_setup(args.setup)
        devices = build_devices(setup, clock_for(setup))
        camera = devices.camera
        camera.open()
        try:
            info = record(camera, args.out, args.pairs, timeout_s=args.timeout_s, codec=args.codec)
        finally:
            camera.close()
    except (HilError, OSError) as exc:
        print(f"record: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"recording": str(info.directory), "pairs": info.pairs, "codec": info.codec,
                      "image_size": list(info.image_size), "frame_rate_hz": info.frame_rate_hz}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
