"""``tools/bench host`` probes what the machine grants a real-time loop with fixed work: the figures
from the per-period arrays exactly, and the command's contract (a smoke run with its JSON, a bad
argument refused). No timing asserts: the machine is shared."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.soak.probe import figures, probe_in_subprocess

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "benchmarks" / "bench_host.py"


def test_figures_from_the_per_period_arrays() -> None:
    period = 2_000_000
    wall = np.array([500_000, 500_000, 1_100_000, 2_500_000, 500_000], dtype=np.int64)
    cpu = np.array([500_000, 490_000, 600_000, 700_000, 500_000], dtype=np.int64)
    wake = np.array([10_000, 2_000_001, 5_000, 2_000_000, 0], dtype=np.int64)
    starts = np.array([0, 4_000_001, 6_000_000, 8_000_000, 12_500_000], dtype=np.int64)
    f = figures(wall, cpu, wake, starts, period)
    assert f == {
        "periods": 5,
        "work_wall_ms": {"p50": 0.5, "p99": 2.444, "max": 2.5},
        "work_cpu_ms": {"p50": 0.5, "max": 0.7},
        "stretched_over_2x": 2,            # 1.1 and 2.5 ms against a 0.5 ms median
        "work_over_a_period": 1,
        "woke_late": 1,                    # exactly a period late is not late
        "longest_wake_delay_ms": 2.0,
        "intervals": 4,
        "late": 2,                         # 4.000001 and 4.5 ms
        "late_fraction": 0.5,
        "longest_interval_ms": 4.5,
    }


def test_bench_host_json() -> None:
    proc = subprocess.run([sys.executable, str(SCRIPT), "--json", "--seconds", "0.3", "--work-ms", "0.2"],
                          capture_output=True, text=True, timeout=100, check=False)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert (report["rate_hz"], report["periods"], report["intervals"]) == (500.0, 150, 149)
    assert report["work_units"] >= 1
    w = report["work_wall_ms"]
    assert 0 < w["p50"] <= w["p99"] <= w["max"]
    assert 0 <= report["late"] <= report["intervals"]
    assert set(report["rt_granted"]) >= {"requested", "fifo_priority", "cpu"}
    assert set(report["host_steal_percent"]) == {"loop_cpu", "all_cpus"}


def test_bench_host_refuses_work_longer_than_the_period() -> None:
    proc = subprocess.run([sys.executable, str(SCRIPT), "--work-ms", "3"], capture_output=True, text=True,
                          timeout=100, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("tools/bench host: need seconds > 0, rate > 0 and 0 < work-ms < the "
                                   "period (got 30.0, 500.0, 3.0)")


def test_the_soak_runs_the_probe_in_a_process_of_its_own() -> None:
    out = probe_in_subprocess(0.2, 250.0, 0.2)
    assert (out["periods"], out["intervals"], out["rate_hz"], out["seconds"]) == (50, 49, 250.0, 0.2)
    assert out["rt_summary"]


def test_a_failed_probe_says_why() -> None:
    with pytest.raises(RuntimeError) as info:
        probe_in_subprocess(0.2, 500.0, 5.0)
    assert str(info.value) == ("host probe failed: python -m hil.soak.probe: need seconds > 0, rate > 0 "
                               "and 0 < work-ms < the period (got 0.2, 500.0, 5.0)")


def test_hil_soak_prints_the_probe_beside_its_own_figures() -> None:
    from hil.cli.cmd_soak import _probe_text

    p = {"seconds": 10.0, "intervals": 4999, "late": 5, "late_per_10k": 10.0, "longest_interval_ms": 9.075,
         "work_wall_ms": {"p50": 0.5, "p99": 0.9, "max": 9.0}, "stretched_over_2x": 40,
         "host_steal_percent": {"loop_cpu": 0.4, "all_cpus": 0.2}, "rt_summary": "SCHED_FIFO 80"}
    assert _probe_text(p) == "5 late of 4999 (10 in 10,000), longest 9.075 ms, steal 0.4 %"
    assert _probe_text({"error": "host probe failed: x"}) == "n/a (host probe failed: x)"


def test_hil_soak_refuses_a_negative_probe_time() -> None:
    proc = subprocess.run([sys.executable, "-m", "hil", "soak", "--probe-host", "-1"], capture_output=True,
                          text=True, timeout=100, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "hil soak: --probe-host must be >= 0 s, got -1.0"
