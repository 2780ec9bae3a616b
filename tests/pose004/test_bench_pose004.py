"""The seed-004 benchmark runs and reports its sections (a smoke test, no timing asserts)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "benchmarks" / "bench_pose004.py"


def test_bench_pose004_json() -> None:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--json", "--trials", "8"],
        capture_output=True,
        text=True,
        timeout=110,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert set(report) == {"collinear", "cylinder", "stereotaxy", "trials", "seed"}
    st = report["stereotaxy"]
    assert st["position_error_at_cube_mm"]["lm"]["max"] < 2.0
    assert set(report["cylinder"]) >= {"radius_1mm", "noise_px"}
    assert report["collinear"]["spacing_40mm"]["stereo_direction_deg"]["median"] < 3.0
