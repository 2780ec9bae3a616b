"""The benchmark scripts under tools/benchmarks loaded as modules, for the tests of their
arithmetic and their command lines (they are scripts, not a package)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

BENCHMARKS = Path(__file__).resolve().parents[1] / "tools" / "benchmarks"


def load_bench(name: str, module_name: str) -> ModuleType:
    """``tools/benchmarks/<name>.py`` executed as a fresh module called ``module_name``.

    Raises:
        FileNotFoundError: no such script.
    """
    spec = importlib.util.spec_from_file_location(module_name, BENCHMARKS / f"{name}.py")
    assert spec is not None
    assert spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
