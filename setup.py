"""Build of the compiled kernels: the vision kernel (hil/vision/_kernel.c) and the per-pair
marker geometry with the simulated arm's servo-step kinematics (hil/geometry/_native.c);
everything else is in pyproject.toml.

-O2 without -ffast-math and without floating-point contraction: a kernel must give the numpy
reference's results to rounding (hil/vision/kernel.py, hil/geometry/native.py). Only the Python
C API and the buffer protocol are used: no numpy headers at build time.
"""

from setuptools import Extension, setup

_FLAGS = ["-O2", "-fno-fast-math", "-ffp-contract=off", "-Wall"]

setup(
    ext_modules=[
        Extension(
            "hil.vision._kernel",
            sources=["hil/vision/_kernel.c"],
            extra_compile_args=_FLAGS,
        ),
        Extension(
            "hil.geometry._native",
            sources=["hil/geometry/_native.c"],
            extra_compile_args=_FLAGS,
        ),
    ]
)
