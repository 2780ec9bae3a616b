"""``tools/bench estimators``: the JSON's shape (every estimator, alone and followed by the surrogate
target model, its cost beside rigid's, the kernel that ran); a bad argument is one usage error and
exit 2. No timing is asserted (a shared machine)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "benchmarks" / "bench_estimators.py"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=120,
                          check=False)


def test_json_has_every_estimator() -> None:
    proc = _run("--calls", "100", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert (out["markers"], out["calls"], out["budget_over_rigid_ms"]) == (6, 100, 0.2)
    assert list(out["estimators"]) == ["rigid", "weighted", "local-tps", "pattern", "rigid+surrogate",
                                       "weighted+surrogate", "local-tps+surrogate", "pattern+surrogate"]
    for row in out["estimators"].values():
        assert set(row) == {"p50_ms", "p99_ms", "max_ms", "over_rigid_p50_ms"}
        assert 0.0 < row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]
    assert out["estimators"]["rigid"]["over_rigid_p50_ms"] == 0.0
    assert out["kernel"] == "compiled kernel"


def test_numpy_times_the_reference_code() -> None:
    proc = _run("--calls", "100", "--json", "--numpy")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["kernel"] == "numpy (--numpy)"
    assert len(out["estimators"]) == 8


def test_too_few_markers_is_a_usage_error() -> None:
    proc = _run("--markers", "3")
    assert proc.returncode == 2
    assert "--markers must be >= 4" in proc.stderr
