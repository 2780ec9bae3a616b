"""Type stub of the compiled per-pair geometry (hil/geometry/_native.c); the docstrings there state
the contract."""

from typing import Any

def horn(fixed: Any, moving: Any, R: Any, t: Any, residuals: Any) -> float: ...
def track(points: Any, predicted: Any, tolerance_mm: float, out: Any) -> bool: ...
