"""``tools/bench entry``: each estimator's entry error with the markers' true positions, through the
script as a user runs it; a body with no 4D CT is one line, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "benchmarks" / "bench_entry.py"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=120,
                          check=False)


def test_json_has_every_estimator_and_the_pattern_is_nearest() -> None:
    proc = _run("--seeds", "1", "--seconds", "4", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert (out["seeds"], out["first_seed"], out["seconds"]) == (1, 1, 4.0)
    rows = out["estimators"]
    assert list(rows) == ["rigid", "weighted", "local-tps", "pattern"]
    for row in rows.values():
        assert row["samples"] == 60                       # 4 s at 15 Hz
        assert 0.0 <= row["p50_mm"] <= row["p95_mm"] <= row["max_mm"]
    assert rows["pattern"]["p95_mm"] < 0.5 * rows["local-tps"]["p95_mm"]


def test_a_rigid_phantom_is_one_line() -> None:
    proc = _run("--config", "configs/sim.toml", "--seeds", "1", "--seconds", "1")
    assert proc.returncode == 2
    assert proc.stderr == ("tools/bench entry: error: a 4D CT of a rigid phantom: [simulation.body] model "
                           "is 'rigid'\n")
