"""``hil check-config FILE [--json]``: validate a setup and print it resolved.

Exit 0 when valid (the resolved setup on stdout, warnings such as missing calibration files on
stderr); exit 2 with one ``file: key.path: reason`` line per problem otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil.config.loader import default_setup_path, load_setup
from hil.config.setup import SetupConfig


def warnings(setup: SetupConfig) -> list[str]:
    """Things that are valid but will fail later (files that do not exist yet)."""
    out = []
    stereo = setup.calibration.stereo
    if stereo is not None and not stereo.is_file():
        out.append(f"calibration.stereo: file does not exist yet: {stereo}")
    return out


def run(args: argparse.Namespace) -> int:
    path = args.file if args.file is not None else default_setup_path()
    setup = load_setup(path)
    warns = warnings(setup)
    for w in warns:
        print(f"hil check-config: warning: {path}: {w}", file=sys.stderr)
    resolved: dict[str, Any] = {"file": str(path), "valid": True, "warnings": warns,
                                "setup": setup.resolved()}
    if args.json:
        json.dump(resolved, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(f"{path}: valid")
        _print_tree(resolved["setup"], "")
    return 0


def _print_tree(value: Any, prefix: str) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            _print_tree(v, key)
    else:
        print(f"{prefix} = {json.dumps(value)}")


def add_parser(sub: Any) -> None:
    p = sub.add_parser("check-config", help="validate a setup file and print it resolved",
                       description="Validate a setup TOML file against the driver registry; print "
                                   "the resolved setup, or one line per problem (exit 2).")
    p.add_argument("file", nargs="?", default=None,
                   help="setup TOML (default: the embedded configs/sim.toml)")
    p.add_argument("--json", action="store_true", help="print the resolved setup as JSON")
    p.set_defaults(func=run)
