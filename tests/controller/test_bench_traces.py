"""``tools/bench accuracy`` with ``--trace`` more than once (issue 41's "on every trace"): each
trace's result, the summary over them, and a trace the setup refuses reported beside the others."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from tests.benchtools import load_bench

CONFIG = Path("configs/sim_patient.toml")


def _bench() -> ModuleType:
    return load_bench("bench_accuracy", "bench_accuracy_traces")


def _column(follow: float | None, **more: float) -> dict[str, Any]:
    return {"comp_err_mm_p95": follow, "comp_entry_err_mm_p95_following": 0.2, "lock_err_mm_rms": 0.3,
            "target_err_mm_p95": 1.0, "gate_false_open_rate": 0.0, **more}


def test_the_summary_judges_the_calibrated_column_and_leaves_out_the_refused() -> None:
    results = [
        {"trace": "a/Lung 1.txt", **_column(0.8), "calibrated": _column(0.6, target_err_mm_p95=1.4)},
        {"trace": "b/LIGHT_High_Motion", **_column(2.1, gate_false_open_rate=0.02)},
        {"trace": "c/Prostate.txt", "error": "no breaths"},
        {"trace": "d/Liver 2.txt", **_column(1.0, lock_err_mm_rms=0.5)},
    ]
    s = _bench()._trace_summary(results)
    assert s["traces"] == 4
    assert s["ran"] == 3
    assert s["failed"] == [{"trace": "c/Prostate.txt", "error": "no breaths"}]
    assert s["comp_err_mm_p95_median"] == 1.0            # 0.6 (calibrated), 2.1, 1.0
    assert s["comp_err_mm_p95_max"] == 2.1
    assert s["comp_err_mm_p95_worst_trace"] == "b/LIGHT_High_Motion"
    assert s["traces_within_1mm"] == 2                   # 1.0 is within
    assert s["lock_err_mm_rms_max"] == 0.5
    assert s["target_err_mm_p95_max"] == 1.4             # the calibrated column's, not the CAD one's
    assert s["gate_false_open_rate_max"] == 0.02
    assert s["comp_entry_err_mm_p95_following_max"] == 0.2


def test_no_trace_ran_leaves_the_figures_empty() -> None:
    s = _bench()._trace_summary([{"trace": "x", "error": "unreadable"}])
    assert s["ran"] == 0
    assert s["traces_within_1mm"] == 0
    for key in ("comp_err_mm_p95_median", "comp_err_mm_p95_max", "comp_err_mm_p95_worst_trace",
                "lock_err_mm_rms_max", "target_err_mm_p95_max", "gate_false_open_rate_max"):
        assert s[key] is None, key


def _surrogate(path: Path, breathing: bool) -> Path:
    """A 1-D respiratory trace (docs/traces.md ``surrogate``), 120 s at 25 Hz: a 4 s breath, or flat."""
    rows = [f"{k / 25:.2f} {5.0 * (1.0 - math.cos(2.0 * math.pi * k / 100)) if breathing else 0.0:.4f}"
            for k in range(3000)]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_each_trace_runs_and_a_refused_one_is_named_beside_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Through the real procedure on one trace; the flat one gives no 4D CT for the pattern
    estimator and a missing file nothing at all: both named with their reasons, exit 2."""
    breathing = _surrogate(tmp_path / "breathing.txt", True)
    flat = _surrogate(tmp_path / "flat.txt", False)
    missing = tmp_path / "missing.txt"
    code = _bench().main(["--config", str(CONFIG), "--runs", "1", "--follow-s", "2", "--no-rig-calibration",
                          "--estimator", "pattern", "--json", "--trace", str(breathing), "--trace", str(flat),
                          "--trace", str(missing)])
    captured = capsys.readouterr()
    assert code == 2
    out = json.loads(captured.out)
    ran, refused, absent = out["traces"]
    assert ran["trace"] == str(breathing)
    assert ran["runs_done"] == 1
    assert ran["estimator"] == "pattern"
    assert "no phases for the surrogate target model or the pattern estimator" in refused["error"]
    assert refused["error"].endswith(f"{flat}: the trace does not move (5th and 95th percentiles equal)")
    assert absent["error"] == f"{missing}: no such file or directory"
    s = out["summary"]
    assert s["ran"] == 1
    assert s["comp_err_mm_p95_max"] == ran["comp_err_mm_p95"]
    assert s["comp_err_mm_p95_worst_trace"] == str(breathing)
    assert [f["trace"] for f in s["failed"]] == [str(flat), str(missing)]
    assert "trace 1/3 breathing: following p95" in captured.err
    assert "trace 2/3 flat: error:" in captured.err


def test_the_text_table_gives_a_row_per_trace_and_the_reason_of_a_refused_one(
        capsys: pytest.CaptureFixture[str]) -> None:
    bench = _bench()
    results = [{"trace": "dir/LIGHT_High_Motion", **_column(2.111)},
               {"trace": "p/Prostate 1.txt", "error": "no breaths"}]
    bench._print_traces(results, bench._trace_summary(results))
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split() == ["LIGHT_High_Motion", "2.111", "0.200", "n/a", "0.300", "1.000", "0.000"]
    assert lines[2].split() == ["Prostate", "1", "error:", "no", "breaths"]
    assert lines[3] == ("following p95 over 1 traces: median 2.111 mm, worst 2.111 mm (LIGHT_High_Motion), "
                        "within 1 mm on 0 of 1")
    assert lines[5] == "1 trace(s) refused (above); the figures are over the others"
