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

from types import ModuleType

from hil.compiled import CompiledKernel

_KERNEL = CompiledKernel("hil.vision._kernel", "HIL_VISION_KERNEL")
#: the extension module (None when not built), for tests that call it directly
_module = _KERNEL.module


def active() -> ModuleType | None:
    """The compiled kernel module when it is built and selected, else None (numpy code)."""
    return _KERNEL.active()


def use_kernel(on: bool) -> bool:
    """Select the compiled kernel (``on``, when built) or the numpy code; returns the previous
    selection. Not thread-safe: for tests and benchmarks, between locate calls."""
    return _KERNEL.use(on)


def kernel_status() -> str:
    """One line: whether the kernel is built and selected."""
    return _KERNEL.status()
