"""Run every benchmark in tools/benchmarks and print our figures next to their baselines and
physical bounds, as ratios, in one table.

Run: ``tools/bench all [--quick] [--only NAME ...] [--json]``

Each ``bench_NAME.py`` (except this one) runs in its own process with ``--json`` (``--quick``
passes smaller sample counts); the figures below are picked from its JSON. A benchmark this file
does not know yet still runs and is listed, without figures. What each figure means:
docs/benchmarks.md.

Ratio column: ``ours / reference``. For times and errors lower is better (< 1 beats a baseline;
for an error against its noise-implied lower bound, 1.0 is the best possible); for throughput
(pairs/s) higher is better.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
SEEDS_ACCURACY_MM = 2.0  # the seeds' positioning accuracy (seed 000 ~2 mm; seed 003 2.13 mm)

#: Extra arguments for --quick (smaller samples; same figures, wider confidence).
QUICK_ARGS: dict[str, list[str]] = {
    "vision": ["--pairs", "12", "--passes", "2"],
    "registration": ["--trials", "5"],
    "accuracy": ["--runs", "2"],
    "loop": ["--seconds", "20"],
    "step": ["--periods", "500", "--repeats", "3"],
    "host": ["--seconds", "10"],
    "pose004": ["--trials", "60"],
}


@dataclass(frozen=True)
class Figure:
    bench: str
    name: str
    unit: str
    ours: Callable[[dict[str, Any]], Any]
    reference: Callable[[dict[str, Any]], Any]
    reference_name: str
    higher_is_better: bool = False


def _get(*path: str | int) -> Callable[[dict[str, Any]], Any]:
    def f(d: dict[str, Any]) -> Any:
        node: Any = d
        for p in path:
            if isinstance(node, dict) and p in node:
                node = node[p]
                continue
            if not (isinstance(node, list) and isinstance(p, int) and -len(node) <= p < len(node)):
                return None
            node = node[p]
        return node

    return f


def _const(v: float) -> Callable[[dict[str, Any]], Any]:
    return lambda _d: v


FIGURES: list[Figure] = [
    Figure(
        "vision",
        "stereo pairs/s (1 core CPU)",
        "pairs/s",
        _get("pairs_per_s"),
        _get("baseline_pairs_per_s"),
        "plain OpenCV pipeline",
        higher_is_better=True,
    ),
    Figure(
        "vision",
        "ROI tracking pairs/s (1 core CPU)",
        "pairs/s",
        _get("tracking_pairs_per_s"),
        _get("sequence", "baseline", "pairs_per_s"),
        "plain OpenCV pipeline (same sequence)",
        higher_is_better=True,
    ),
    Figure(
        "vision",
        "3D marker error RMS",
        "mm",
        _get("err3d_mm_rms"),
        _get("err3d_bound_mm"),
        "noise-implied bound (Cramer-Rao)",
    ),
    Figure(
        "vision",
        "3D marker error RMS",
        "mm",
        _get("err3d_mm_rms"),
        _get("baseline_err3d_mm_rms"),
        "plain OpenCV pipeline",
    ),
    Figure(
        "vision",
        "centre error RMS",
        "px",
        _get("center_err_px_rms"),
        _get("center_err_bound_px"),
        "noise-implied bound (Cramer-Rao)",
    ),
    Figure(
        "vision",
        "centre error RMS",
        "px",
        _get("center_err_px_rms"),
        _get("paper_center_err_px_rms"),
        "seed 001 pipeline",
    ),
    Figure(
        "registration",
        "ICP time, principal-axes start",
        "ms",
        _get("icp", "principal", "median_time_ms"),
        _get("icp", "identity", "median_time_ms"),
        "plain ICP (ours, identity start)",
    ),
    Figure(
        "registration",
        "ICP success rate",
        "",
        _get("icp", "principal", "success_rate"),
        _get("icp", "identity", "success_rate"),
        "plain ICP (ours, identity start)",
        higher_is_better=True,
    ),
    Figure(
        "registration",
        "Horn registration, 8 points",
        "us",
        _get("paired", "n8", "horn_us"),
        _get("paired", "n8", "svd_us"),
        "SVD (Arun/Umeyama)",
    ),
    Figure(
        "accuracy",
        "guide error at lock, RMS (truth)",
        "mm",
        _get("lock_err_mm_rms"),
        _const(SEEDS_ACCURACY_MM),
        "seeds' ~2 mm",
    ),
    Figure(
        "accuracy",
        "guide error at lock, max (truth)",
        "mm",
        _get("lock_err_mm_max"),
        _const(SEEDS_ACCURACY_MM),
        "seeds' ~2 mm",
    ),
    Figure(
        "accuracy",
        "compensation error p95 (truth)",
        "mm",
        _get("comp_err_mm_p95"),
        _const(SEEDS_ACCURACY_MM),
        "seeds' ~2 mm",
    ),
    Figure(
        "loop", "servo jitter p99", "ms", _get("jitter_ms", "p99"), _get("period_ms"), "robot servo period"
    ),
    Figure(
        "loop", "servo jitter max", "ms", _get("jitter_ms", "max"), _get("period_ms"), "robot servo period"
    ),
    Figure(
        "loop", "longest servo gap", "ms", _get("longest_gap_ms"), _get("period_ms"), "robot servo period"
    ),
    Figure("loop", "missed servo deadlines", "fraction", _get("missed_fraction"), _const(0.0), "none"),
    Figure(
        "loop",
        "frame-to-command latency p50",
        "ms",
        _get("frame_to_command_ms", "p50"),
        _const(1e3 / 15.0),
        "camera frame period (15 Hz)",
    ),
    Figure(
        "step",
        "servo period CPU (simulated arm, 500 Hz)",
        "us",
        _get("cpu_per_period_us", "median"),
        _get("period_us"),
        "robot servo period",
    ),
    Figure(
        "host",
        "late intervals, fixed work alone (the machine)",
        "fraction",
        _get("late_fraction"),
        _const(1e-4),
        "1 in 10,000 (issue 16)",
    ),
    Figure(
        "pose004",
        "stereo needle tip, 20 mm spacing, median",
        "mm",
        _get("collinear", "spacing_20mm", "stereo_tip_position_mm", "median"),
        _const(SEEDS_ACCURACY_MM),
        "seeds' ~2 mm",
    ),
    Figure(
        "prediction",
        "best predictor RMS, 15 Hz, 60 ms (recorded breathing)",
        "mm",
        lambda d: _get("predictors", str(d.get("default")), "rmse_mm")(d),
        _get("predictors", "alpha-beta", "rmse_mm"),
        "today's alpha-beta filter",
    ),
    Figure(
        "prediction",
        "best predictor RMS, 15 Hz, 60 ms (recorded breathing)",
        "mm",
        lambda d: _get("predictors", str(d.get("default")), "rmse_mm")(d),
        _get("predictors", "none", "rmse_mm"),
        "no prediction",
    ),
]


def discover() -> list[str]:
    return sorted(p.stem.removeprefix("bench_") for p in HERE.glob("bench_*.py") if p.stem != "bench_all")


def run_bench(name: str, quick: bool, timeout_s: float) -> tuple[dict[str, Any] | None, str, float]:
    """(JSON result or None, error text, wall seconds)."""
    cmd = [
        sys.executable,
        str(HERE / f"bench_{name}.py"),
        "--json",
        *(QUICK_ARGS.get(name, []) if quick else []),
    ]
    t0 = time.monotonic()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return None, f"timed out after {timeout_s:.0f} s", time.monotonic() - t0
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return None, f"exit {proc.returncode}: {tail}", wall
    try:
        lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
        text = proc.stdout if proc.stdout.lstrip().startswith("{") and len(lines) > 1 else lines[-1]
        return json.loads(text), "", wall
    except (json.JSONDecodeError, IndexError):
        return None, "no JSON on stdout", wall


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def rows_for(name: str, data: dict[str, Any]) -> list[dict[str, Any]]:
    out = []
    for f in FIGURES:
        if f.bench != name:
            continue
        ours, ref = _num(f.ours(data)), _num(f.reference(data))
        ratio = None if ours is None or ref is None or ref == 0 else ours / ref
        out.append(
            {
                "bench": name,
                "figure": f.name,
                "unit": f.unit,
                "ours": ours,
                "reference": ref,
                "reference_name": f.reference_name,
                "ratio": ratio,
                "better": "higher" if f.higher_is_better else "lower",
            }
        )
    return out


def _fmt(v: float | None) -> str:
    if v is None:
        return "n/a"
    return f"{v:.4g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench all", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller samples (minutes instead of tens)")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run only these benchmarks")
    ap.add_argument("--timeout", type=float, default=1800.0, help="per benchmark, s (default 1800)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    names = discover()
    if args.only:
        unknown = sorted(set(args.only) - set(names))
        if unknown:
            print(f"tools/bench all: unknown benchmark(s) {unknown}; available: {names}", file=sys.stderr)
            return 2
        names = [n for n in names if n in args.only]
    rows: list[dict[str, Any]] = []
    runs: dict[str, dict[str, Any]] = {}
    for name in names:
        print(f"tools/bench all: running {name} ...", file=sys.stderr, flush=True)
        data, err, wall = run_bench(name, args.quick, args.timeout)
        runs[name] = {"ok": data is not None, "error": err, "wall_s": round(wall, 1)}
        if data is not None:
            got = rows_for(name, data)
            rows += got
            runs[name]["figures"] = len(got)
    if args.json:
        print(json.dumps({"benchmarks": runs, "figures": rows}))
        return 0 if all(r["ok"] for r in runs.values()) else 1
    headers = ["benchmark", "figure", "ours", "reference", "ratio", "reference is"]
    table = [
        [
            r["bench"],
            f"{r['figure']} [{r['unit']}]" if r["unit"] else r["figure"],
            _fmt(r["ours"]),
            _fmt(r["reference"]),
            "n/a" if r["ratio"] is None else f"{r['ratio']:.3g}" + (" ^" if r["better"] == "higher" else ""),
            r["reference_name"],
        ]
        for r in rows
    ]
    widths = [
        max(len(h), *(len(row[i]) for row in table)) if table else len(h) for i, h in enumerate(headers)
    ]
    print("  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)))
    for row in table:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)))
    print("(ratio = ours / reference; ^ marks figures where higher is better)")
    for name, r in runs.items():
        status = "ok" if r["ok"] else f"FAILED ({r['error']})"
        extra = "" if not r["ok"] or r.get("figures") else ", no figures extracted"
        print(f"{name}: {status}, {r['wall_s']} s{extra}")
    return 0 if all(r["ok"] for r in runs.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
