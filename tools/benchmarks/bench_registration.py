"""Benchmark the geometry core: paired registration, ICP (vs plain ICP), marker matching.

Run: ``.venv/bin/python tools/benchmarks/bench_registration.py [--json] [--trials N] [--seed S]``

Prints time and accuracy of each method next to its baseline:
- Horn vs SVD paired registration (time per call; agreement);
- ICP with the principal-axes start vs plain ICP from the identity, over random rotations of
  uniformly distributed angle (success = rotation error < 0.1 degree);
- correspondence-free matching of 6 markers with one missing and one spurious point.
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

from hil.geometry.icp import icp
from hil.geometry.matching import match_markers
from hil.geometry.registration import register_horn, register_svd
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--trials", type=int, default=20, help="ICP/matching trials (default 20)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    report = {
        "paired": bench_paired(rng),
        "icp": bench_icp(rng, args.trials),
        "matching": bench_matching(rng, args.trials),
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
