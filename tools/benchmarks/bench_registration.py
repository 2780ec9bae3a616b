"""Benchmark the geometry core: paired registration, ICP (vs plain ICP), marker matching.

Run: ``.venv/bin/python tools/benchmarks/bench_registration.py [--json] [--trials N] [--seed S]``

Prints time and accuracy of each method next to its baseline:
- Horn vs SVD paired registration (time per call; agreement);
- ICP with the principal-axes start vs plain ICP from the identity, over random rotations of
  uniformly distributed angle (success = rotation error < 0.1 degree);
- correspondence-free matching of 6 markers with one missing and one spurious point;
- the per-pair marker geometry (Horn on 6 markers, tracking 6 markers among 10 points), compiled
  (hil/geometry/_native.c) beside its numpy reference, hot (back to back) and *cold*: one call
  every 10 ms and every 33 ms (a camera period), as the controller calls it. On a shared host
  code that ran 33 ms ago has been evicted from the caches (docs/benchmarks.md, "Issue 16: cold
  code on the pair's path"); ``--cold-calls`` sets how many spaced calls are timed.
Wall-clock figures depend on the machine; the accuracy figures do not (fixed seed).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from typing import Any, Literal

import numpy as np

from hil.controller.registration import track, track_numpy
from hil.geometry import native
from hil.geometry.icp import icp
from hil.geometry.matching import match_markers
from hil.geometry.registration import register_horn, register_horn_numpy, register_svd
from hil.geometry.transform import RigidTransform


def _random_rotation(rng: np.random.Generator) -> RigidTransform:
    q = rng.normal(size=4)
    return RigidTransform.from_quaternion(q, rng.uniform(-50, 50, size=3))


def _time_us(fn: Callable[[], object], repeat: int) -> float:
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat * 1e6


def bench_paired(rng: np.random.Generator) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for n in (4, 8, 100):
        moving = rng.uniform(-100, 100, size=(n, 3))
        T = _random_rotation(rng)
        fixed = T.apply(moving) + rng.normal(scale=0.3, size=(n, 3))
        h = register_horn(fixed, moving)
        s = register_svd(fixed, moving)
        d = h.T_fixed_from_moving.inverse() @ s.T_fixed_from_moving
        out[f"n{n}"] = {
            "horn_us": round(_time_us(partial(register_horn, fixed, moving), 300), 1),
            "svd_us": round(_time_us(partial(register_svd, fixed, moving), 300), 1),
            "horn_vs_svd_rotation_rad": d.rotation_angle_rad(),
            "fre_rms_mm": round(h.fre_rms_mm, 4),
        }
    return out


def _surface(n: int, rng: np.random.Generator) -> np.ndarray:
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    bump = 15.0 * np.exp(-np.sum((u - np.array([0.6, 0.6, 0.5])) ** 2, axis=1) / 0.1)
    out: np.ndarray = u * np.array([60.0, 35.0, 20.0]) + u * bump[:, None]
    return out


def bench_icp(rng: np.random.Generator, trials: int) -> dict[str, Any]:
    target = _surface(3000, rng)
    results: dict[str, dict[str, list[float]]] = {
        "principal": {"time_ms": [], "rot_err_deg": [], "iterations": []},
        "identity": {"time_ms": [], "rot_err_deg": [], "iterations": []},
    }
    modes: tuple[Literal["principal"], Literal["identity"]] = ("principal", "identity")
    for _ in range(trials):
        src_true = _surface(600, rng) + rng.normal(scale=0.2, size=(600, 3))  # a different sampling
        T = _random_rotation(rng)
        src = T.inverse().apply(src_true)
        for mode in modes:
            t0 = time.perf_counter()
            r = icp(src, target, init=mode)
            dt = (time.perf_counter() - t0) * 1e3
            err = math.degrees((r.T_target_from_source.inverse() @ T).rotation_angle_rad())
            results[mode]["time_ms"].append(dt)
            results[mode]["rot_err_deg"].append(err)
            results[mode]["iterations"].append(r.iterations)
    summary: dict[str, Any] = {"trials": trials, "source_points": 600, "target_points": 3000}
    for name, res in results.items():
        errs = res["rot_err_deg"]
        ok = [e for e in errs if e < 2.0]
        summary[name] = {
            "success_rate": round(len(ok) / trials, 3),
            "median_rot_err_deg_of_successes": round(statistics.median(ok), 4) if ok else None,
            "median_time_ms": round(statistics.median(res["time_ms"]), 2),
            "median_iterations": statistics.median(res["iterations"]),
        }
    summary["success_criterion"] = "rotation error < 2 deg (source resampled + 0.2 mm noise)"
    return summary


def bench_matching(rng: np.random.Generator, trials: int) -> dict[str, Any]:
    model = np.array(
        [[0.0, 0.0, 0.0], [80.0, 0.0, 5.0], [20.0, 60.0, -3.0], [-30.0, 45.0, 10.0], [55.0, 70.0, 0.0],
         [10.0, -40.0, 8.0]]
    )
    correct = 0
    times = []
    for _ in range(trials):
        T = _random_rotation(rng)
        meas = T.apply(model) + rng.normal(scale=0.3, size=model.shape)
        missing = int(rng.integers(6))
        keep = [i for i in range(6) if i != missing]
        meas = np.vstack([meas[keep], T.apply([150.0, -80.0, 30.0])])
        t0 = time.perf_counter()
        m = match_markers(meas, model)
        times.append((time.perf_counter() - t0) * 1e3)
        correct += int(m.model_to_measured == {k: j for j, k in enumerate(keep)} and not m.ambiguous)
    median_ms = round(statistics.median(times), 2)
    return {"trials": trials, "correct_rate": correct / trials, "median_time_ms": median_ms}


def _spaced_us(fn: Callable[[], object], spacing_s: float, calls: int) -> float:
    """Median time of one call of ``fn`` made ``spacing_s`` after the previous one, µs."""
    times = []
    for _ in range(calls):
        time.sleep(spacing_s)
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return round(statistics.median(times) * 1e-3, 1)


def bench_per_pair(rng: np.random.Generator, cold_calls: int) -> dict[str, Any]:
    """The controller's per-pair geometry, compiled and numpy, hot and cold (module doc)."""
    moving = rng.uniform(-60, 60, size=(6, 3))
    fixed = _random_rotation(rng).apply(moving) + rng.normal(scale=0.1, size=(6, 3))
    points = np.vstack([fixed, rng.uniform(-200, 200, size=(4, 3))])
    predicted = fixed + rng.normal(scale=0.5, size=(6, 3))
    built = native.is_built()
    previous = native.use_native(True)
    try:
        variants: dict[str, dict[str, Callable[[], object]]] = {
            "horn": {"compiled": partial(register_horn, fixed, moving),
                     "numpy": partial(register_horn_numpy, fixed, moving)},
            "track": {"compiled": partial(track, points, predicted, 6.0),
                      "numpy": partial(track_numpy, points, predicted, 6.0)},
        }
        out: dict[str, Any] = {"native": native.native_status(), "cold_calls": cold_calls}
        for what, fns in variants.items():
            out[f"{what}_us"] = {}
            for kind, fn in fns.items():
                if kind == "compiled" and not built:
                    continue
                for _ in range(200):   # warm-up
                    fn()
                out[f"{what}_us"][kind] = {
                    "hot": round(_time_us(fn, 300), 1),
                    "every_10ms": _spaced_us(fn, 0.010, cold_calls),
                    "every_33ms": _spaced_us(fn, 0.0333, cold_calls),
                }
    finally:
        native.use_native(previous)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--trials", type=int, default=20, help="ICP/matching trials (default 20)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cold-calls", type=int, default=100,
                    help="spaced calls timed per per-pair variant (default 100: ~17 s in all)")
    args = ap.parse_args(argv)
    if args.cold_calls < 1:
        ap.error(f"--cold-calls must be >= 1, got {args.cold_calls}")
    rng = np.random.default_rng(args.seed)
    report = {
        "paired": bench_paired(rng),
        "icp": bench_icp(rng, args.trials),
        "matching": bench_matching(rng, args.trials),
        "per_pair": bench_per_pair(rng, args.cold_calls),
    }
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    print("paired registration (N points, 0.3 mm noise):")
    for k, v in report["paired"].items():
        print(f"  {k:>5}: horn {v['horn_us']:8.1f} us   svd {v['svd_us']:8.1f} us   "
              f"|horn - svd| {v['horn_vs_svd_rotation_rad']:.1e} rad   FRE {v['fre_rms_mm']} mm")
    icp_r = report["icp"]
    print(f"ICP over {icp_r['trials']} random rotations ({icp_r['success_criterion']}):")
    for mode in ("principal", "identity"):
        v = icp_r[mode]
        label = "principal-axes start" if mode == "principal" else "plain ICP (baseline)"
        err = v["median_rot_err_deg_of_successes"]
        print(f"  {label:22s} success {v['success_rate']:.0%}   median error {err} deg"
              f"   median {v['median_time_ms']} ms, {v['median_iterations']} iterations")
    mr = report["matching"]
    print(f"matching 6 markers, 1 missing + 1 spurious: {mr['correct_rate']:.0%} correct, "
          f"median {mr['median_time_ms']} ms")
    pp = report["per_pair"]
    print(f"per-pair geometry ({pp['native']}), median us: hot / one call every 10 ms / every 33 ms")
    for what in ("horn", "track"):
        for kind, v in pp[f"{what}_us"].items():
            base = "" if kind == "numpy" else "   (numpy: the baseline below)"
            print(f"  {what:5s} {kind:8s} {v['hot']:7.1f} / {v['every_10ms']:7.1f} / "
                  f"{v['every_33ms']:7.1f}{base}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
