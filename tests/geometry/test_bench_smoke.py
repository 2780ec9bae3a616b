"""The benchmark script runs and reports the expected keys (a smoke test, no timing asserts)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "benchmarks" / "bench_registration.py"


def test_bench_registration_json() -> None:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--json", "--trials", "2", "--cold-calls", "3"],
        capture_output=True, text=True, timeout=100, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert set(report) == {"paired", "icp", "matching", "per_pair"}
    per_pair = report["per_pair"]
    assert per_pair["native"] == "compiled kernel"
    assert per_pair["cold_calls"] == 3
    for what in ("horn_us", "track_us"):
        assert set(per_pair[what]) == {"compiled", "numpy"}
        for v in per_pair[what].values():
            assert set(v) == {"hot", "every_10ms", "every_33ms"}
            assert all(x > 0 for x in v.values())
    assert report["paired"]["n8"]["horn_vs_svd_rotation_rad"] < 1e-9
    assert report["icp"]["principal"]["success_rate"] == 1.0
    assert report["matching"]["correct_rate"] == 1.0
