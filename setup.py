"""Build of the compiled vision kernel (hil/vision/_kernel.c); everything else is in pyproject.toml.

-O2 without -ffast-math and without floating-point contraction: the kernel must give the numpy
reference's results to rounding (hil/vision/kernel.py). Only the Python C API and the buffer
protocol are used: no numpy headers at build time.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "hil.vision._kernel",
            sources=["hil/vision/_kernel.c"],
            extra_compile_args=["-O2", "-fno-fast-math", "-ffp-contract=off", "-Wall"],
        )
    ]
)
