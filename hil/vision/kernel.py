"""The one place that selects the compiled per-ring kernel (``hil/vision/_kernel.c``) or the numpy
reference code for the ring edges and the robust ellipse fits.

The kernel is a CPython extension built by ``pip install -e .`` (setup.py); it does the same
arithmetic as the numpy code (:func:`hil.vision.ring_edges.ring_edges_multi_numpy`,
:func:`hil.vision.ellipse.fit_ellipse_arrays_numpy`) and agrees with it to rounding
(tests/vision/test_kernel.py). ``HIL_VISION_KERNEL=numpy`` in the environment (read at import)
selects the numpy code; :func:`use_kernel` switches at run time (tests, benchmarks). When the
extension is not built the numpy code runs and :func:`kernel_status` says why.
"""

from __future__ import annotations

import os
from types import ModuleType

_module: ModuleType | None
_import_error: str | None
try:
    from hil.vision import _kernel as _module

    _import_error = None
except ImportError as exc:  # not built (e.g. a source tree without `pip install -e .`)
    _module, _import_error = None, str(exc)

_enabled = _module is not None and os.environ.get("HIL_VISION_KERNEL", "").lower() != "numpy"


def active() -> ModuleType | None:
    """The compiled kernel module when it is built and selected, else None (numpy code)."""
    return _module if _enabled else None


def use_kernel(on: bool) -> bool:
    """Select the compiled kernel (``on``, when built) or the numpy code; returns the previous
    selection. Not thread-safe: for tests and benchmarks, between locate calls."""
    global _enabled
    previous = _enabled
    _enabled = bool(on) and _module is not None
    return previous


def kernel_status() -> str:
    """One line: whether the kernel is built and selected."""
    if _module is None:
        return f"numpy (the compiled kernel is not built: {_import_error})"
    return "compiled kernel" if _enabled else "numpy (selected)"
