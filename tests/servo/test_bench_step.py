"""``tools/bench step`` runs the servo loop on the simulated arm and reports its CPU per period (a
smoke test of the benchmark's contract: every period commanded, the figures present; no timing
asserts - the machine is shared)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "benchmarks" / "bench_step.py"


def test_bench_step_json() -> None:
    proc = subprocess.run([sys.executable, str(SCRIPT), "--json", "--periods", "50", "--repeats", "2"],
                          capture_output=True, text=True, timeout=100, check=False)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    facts = (report["rate_hz"], report["period_us"], report["periods"], report["repeats"])
    assert facts == (500.0, 2000.0, 50, 2)
    assert report["servo_commands"] == 200 + 2 * 50   # the warm-up and every measured period
    cpu = report["cpu_per_period_us"]
    assert 0 < cpu["min"] <= cpu["median"] <= cpu["max"]
    assert abs(report["share_of_period"] - cpu["median"] / 2000.0) <= 1e-4   # (both rounded)


def test_bench_step_refuses_a_bad_count() -> None:
    proc = subprocess.run([sys.executable, str(SCRIPT), "--periods", "0"], capture_output=True, text=True,
                          timeout=100, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "tools/bench step: rate, periods and repeats must be > 0 (got 500.0, 0, 5)"
