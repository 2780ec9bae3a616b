"""Selection between a compiled extension and the numpy reference code it stands in for.

Each compiled kernel (``hil/vision/_kernel.c``, ``hil/geometry/_native.c``) is a CPython
extension built by ``pip install -e .`` (setup.py) that agrees with its numpy reference to
rounding. :class:`CompiledKernel` imports it if it was built, lets an environment variable
(``<VAR>=numpy``, read at import) or :meth:`CompiledKernel.use` (tests, benchmarks) select the
numpy code, and says in one line which runs and why.
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType


class CompiledKernel:
    """One compiled extension and whether it is selected.

    Args:
        module: the extension's import name (e.g. ``"hil.geometry._native"``).
        env_var: the environment variable whose value ``numpy`` selects the numpy code.
    """

    def __init__(self, module: str, env_var: str) -> None:
        self.env_var = env_var
        self.module: ModuleType | None
        self.import_error: str | None
        try:
            self.module, self.import_error = importlib.import_module(module), None
        except ImportError as exc:  # not built (e.g. a source tree without `pip install -e .`)
            self.module, self.import_error = None, str(exc)
        self.enabled = self.module is not None and os.environ.get(env_var, "").lower() != "numpy"

    def active(self) -> ModuleType | None:
        """The extension when it is built and selected, else None (the numpy code runs)."""
        return self.module if self.enabled else None

    def use(self, on: bool) -> bool:
        """Select the extension (``on``, when built) or the numpy code; returns the previous
        selection. Not thread-safe: for tests and benchmarks, between calls."""
        previous = self.enabled
        self.enabled = bool(on) and self.module is not None
        return previous

    def status(self) -> str:
        """One line: whether the extension is built and selected."""
        if self.module is None:
            return f"numpy (the compiled kernel is not built: {self.import_error})"
        return "compiled kernel" if self.enabled else "numpy (selected)"
