"""The one place that selects the compiled per-pair geometry (``hil/geometry/_native.c``) or the
numpy reference code: :func:`hil.geometry.registration.register_horn` (unit weights),
:func:`hil.controller.registration.track`, COMPENSATE's control law
(:meth:`hil.controller.compensation.MotionFilter.update_about` and ``estimate``,
:meth:`hil.controller.estimate.Estimate.tracking_setpoint`), the local change estimators' fit
(:mod:`hil.controller.change_estimate`), the surrogate target model's steering
(:mod:`hil.controller.target_model`) and :func:`hil.kinematics.ur.ur_newton_ik`.

All but the last run for every stereo pair between the exposure and the servo setpoint, the last
(the simulated arm's servo command) in every servo period. On a shared host,
numpy code that runs once per camera period takes several times its hot-loop time (its code and
data are evicted in between; docs/benchmarks.md "Issue 16: cold code on the pair's path"); the
compiled code is small and agrees with the numpy code to rounding (tests/geometry/test_native.py).
``HIL_GEOMETRY_KERNEL=numpy`` in the environment (read at import) selects the numpy code;
:func:`use_native` switches at run time (tests, benchmarks). When the extension is not built the
numpy code runs and :func:`native_status` says why.
"""

from __future__ import annotations

from types import ModuleType

from hil.compiled import CompiledKernel

_KERNEL = CompiledKernel("hil.geometry._native", "HIL_GEOMETRY_KERNEL")


def active() -> ModuleType | None:
    """The compiled module when it is built and selected, else None (numpy code)."""
    return _KERNEL.active()


def use_native(on: bool) -> bool:
    """Select the compiled code (``on``, when built) or the numpy code; returns the previous
    selection. Not thread-safe: for tests and benchmarks."""
    return _KERNEL.use(on)


def native_status() -> str:
    """One line: whether the compiled geometry is built and selected."""
    return _KERNEL.status()


def is_built() -> bool:
    """Whether the extension was built (whatever is selected)."""
    return _KERNEL.module is not None
