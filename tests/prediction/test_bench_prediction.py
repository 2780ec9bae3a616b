"""``tools/bench prediction`` on one shared recorded trace: the JSON's keys and the baseline ratio;
bad input is one error line and exit 2. The shared data must be there (the test fails naming the
path when it is not: data/README.md in shared/)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.controller.config import CompensationConfig

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "tools" / "benchmarks" / "bench_prediction.py"
SHARED_DATA = Path(os.environ.get("HIL_SHARED_DATA") or REPO.parent / "shared" / "data")
TRACE = (SHARED_DATA / "respiration" / "interact" / "paired"
    / "LIGHT_SABR_Lung_High_Motion" / "2.High_Motion SI.txt")
NAMES = {"none", "alpha-beta", "wlms", "ar-ls", "kalman-osc", "fast-lane"}


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300,
                          check=False)


def test_shared_trace_is_present() -> None:
    assert TRACE.is_file(), f"shared data missing: {TRACE} (see ../shared/data/README.md)"


def test_bench_json_on_one_shared_trace() -> None:
    assert TRACE.is_file(), f"shared data missing: {TRACE}"
    proc = _run("--trace", str(TRACE), "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["traces"] == 1
    assert out["rate_hz"] == 15.0
    assert out["horizon_ms"] == 60.0
    assert out["noise_mm"] == 0.05
    assert set(out["predictors"]) == NAMES
    for f in out["predictors"].values():
        assert {"rmse_mm", "p95_mm", "max_mm", "ratio_to_none"} <= set(f)
        assert 0 < f["rmse_mm"] <= f["max_mm"]
        assert f["p95_mm"] <= f["max_mm"]
    assert out["predictors"]["none"]["ratio_to_none"] == 1.0
    assert out["default"] == CompensationConfig().predictor   # what the controller runs
    assert out["predictors"][out["default"]]["ratio_to_none"] < 1.0
    assert out["best"] == min(NAMES, key=lambda n: out["predictors"][n]["rmse_mm"])


def test_bench_cost_json() -> None:
    proc = _run("--cost", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert (out["rate_hz"], out["samples"]) == (15.0, 3000)
    assert set(out["cost"]) == NAMES
    for c in out["cost"].values():
        assert set(c) == {"p50_us", "p99_us", "max_us", "mean_us", "cpu_mean_us"}
        assert 0 < c["p50_us"] <= c["p99_us"] <= c["max_us"]
    assert out["default"] == CompensationConfig().predictor


def test_bench_cost_bad_rate() -> None:
    proc = _run("--cost", "--rate", "0")
    assert proc.returncode == 2
    assert proc.stderr.strip() == "tools/bench prediction: error: --rate must be a number > 0 (got 0.0)"


def test_bench_other_condition() -> None:
    assert TRACE.is_file(), f"shared data missing: {TRACE}"
    proc = _run("--trace", str(TRACE), "--rate", "30", "--horizon-ms", "100", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert (out["rate_hz"], out["horizon_ms"]) == (30.0, 100.0)
    assert out["samples"] == round(299.8 * 30) + 1  # the trace spans 0 ... 299.8 s


@pytest.mark.parametrize(("args", "says"), [
    (["--trace", "/nonexistent/trace.txt"], "/nonexistent/trace.txt"),
    (["--rate", "0"], "--rate must be a number > 0"),
    (["--horizon-ms", "500"], "at most 200 ms"),
    (["--max-minutes", "-1"], "--max-minutes must be a number > 0"),
])
def test_bad_input_is_one_line_and_exit_2(args: list[str], says: str) -> None:
    proc = _run(*args, "--json")
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("tools/bench prediction: error: ")
    assert says in lines[0]


def test_a_surrogate_alone_is_refused() -> None:
    resp = TRACE.parent / "2.High_Motion_resp.txt"
    assert resp.is_file(), f"shared data missing: {resp}"
    proc = _run("--trace", str(resp), "--json")
    assert proc.returncode == 2
    assert "holds no 3-D position" in proc.stderr


def test_a_paired_directory_is_a_trace() -> None:
    assert TRACE.is_file(), f"shared data missing: {TRACE}"
    proc = _run("--trace", str(TRACE.parent), "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["traces"] == 1


def test_max_minutes_cuts_each_trace() -> None:
    assert TRACE.is_file(), f"shared data missing: {TRACE}"
    proc = _run("--trace", str(TRACE), "--max-minutes", "1", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["max_minutes"] == 1.0
    assert out["samples"] == 60 * 15 + 1
