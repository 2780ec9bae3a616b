"""argparse value types shared by the subcommands (each raises ArgumentTypeError with the reason)."""

from __future__ import annotations

import argparse
import math


def xyz_mm(text: str) -> tuple[float, float, float]:
    """``X,Y,Z`` -> three finite floats (mm)."""
    try:
        vals = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in mm, got {text!r}") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected three finite numbers X,Y,Z, got {text!r}")
    return vals[0], vals[1], vals[2]
