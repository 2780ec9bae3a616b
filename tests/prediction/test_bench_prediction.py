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


def test_resampling_is_recorded_and_changes_the_samples_between_recorded_ones() -> None:
    """The 5 Hz trace at 15 Hz: the cubic spline and the straight lines agree on the recorded
    samples and differ between them, so the two methods give different errors; the JSON says which."""
    assert TRACE.is_file(), f"shared data missing: {TRACE}"
    outs = {}
    for method in ("cubic", "linear"):
        proc = _run("--trace", str(TRACE), "--max-minutes", "1", "--resample", method, "--json")
        assert proc.returncode == 0, proc.stderr
        outs[method] = json.loads(proc.stdout)
        assert outs[method]["resample"] == method
    assert outs["cubic"]["samples"] == outs["linear"]["samples"]
    rms = {m: o["predictors"]["alpha-beta"]["rmse_mm"] for m, o in outs.items()}
    assert rms["cubic"] != rms["linear"]


def test_resample_cubic_passes_through_the_recorded_samples() -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import bench_prediction as bp
    finally:
        sys.path.remove(str(SCRIPT.parent))
    import numpy as np
    t = np.arange(12) * 0.2
    x = np.stack([np.sin(t), np.cos(2 * t), t * t], axis=1)
    tr = bp.Trace("synthetic", t, x)
    assert np.allclose(bp.truth_at(tr, t, "cubic"), x, atol=1e-12)
    assert np.allclose(bp.truth_at(tr, t, "linear"), x, atol=1e-12)
    mid = t[:-1] + 0.1
    # the spline follows the smooth curve between samples better than straight lines do
    exact = np.stack([np.sin(mid), np.cos(2 * mid), mid * mid], axis=1)
    err_cubic = np.abs(bp.truth_at(tr, mid, "cubic") - exact).max()
    err_linear = np.abs(bp.truth_at(tr, mid, "linear") - exact).max()
    assert err_cubic < 0.1 * err_linear
    with pytest.raises(ValueError, match="--resample must be one of cubic, linear"):
        bp.truth_at(tr, mid, "nearest")


def test_too_few_samples_after_the_cut_is_one_line() -> None:
    assert TRACE.is_file(), f"shared data missing: {TRACE}"
    proc = _run("--trace", str(TRACE), "--max-minutes", "0.005", "--json")
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert "at least 4 are needed" in proc.stderr.strip().splitlines()[0]
