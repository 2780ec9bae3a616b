"""Per-pair cost of the change estimators (issue 41: the pair's path must not grow by more than
0.2 ms p99 at 500 Hz).

Run: ``tools/bench estimators [--json] [--markers N] [--calls N] [--seed S] [--numpy]``

Times :func:`hil.controller.change_estimate.estimate_change` for each estimator on one synthetic
skin (N markers on a gently curved patch, a small rigid change plus 0.5 mm of non-rigid noise),
as the controller calls it once per registered pair (``pattern`` with its rows fitted to the 4D CT
below), and each estimator followed by the surrogate
target model's steering as the loop runs it (``<estimator>+surrogate``: the score, its rate and
the faded turn of hil/controller/target_model.py's ``TargetTracker``, fitted to a synthetic
10-phase 4D CT of the same skin). ``--numpy`` times the numpy reference code instead of the
compiled kernels (hil/geometry/_native.c), as ``HIL_GEOMETRY_KERNEL=numpy`` does. Prints p50 /
p99 / max per row (ms) and each one's p50 beyond ``rigid``'s (the compiled Horn fit the default
runs). The machine's load shows in p99 and max: read them beside the host's state (``uptime``),
or run on an idle machine. The in-situ figures are ``hil soak``'s ``change_fit_us`` (this call in
the loop, where its code runs cold once a camera period) and frame -> command latency, with the
estimator and target model set in the config.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from collections.abc import Callable

import numpy as np

from hil.controller.change_estimate import ChangeEstimator, ChangeFit, estimate_change
from hil.controller.entry_pattern import EntryRows, fit_entry_pattern
from hil.controller.plan_file import PlanPhase, ProcedurePlan
from hil.controller.target_model import SurrogateTargetModel, TargetTracker, fit_target_model
from hil.geometry import native
from hil.geometry.transform import RigidTransform

WARMUP_CALLS = 200


def _skin(markers: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference markers, live markers and the entry (optical frame, mm)."""
    rng = np.random.default_rng(seed)
    ref = rng.uniform(-80.0, 80.0, size=(markers, 3))
    ref[:, 2] = 0.2 * ref[:, 0] + 0.002 * ref[:, 1] ** 2
    change = RigidTransform.from_rotvec([0.01, -0.02, 0.005], [2.0, -1.0, 3.0])
    live = change.apply(ref) + rng.normal(0.0, 0.5, size=ref.shape)
    return ref, live, np.array([5.0, 3.0, 1.0])


def _model(ref: np.ndarray, entry: np.ndarray,
           seed: int) -> tuple[SurrogateTargetModel, EntryRows, ProcedurePlan, np.ndarray]:
    """A surrogate model and the ``pattern`` estimator's rows fitted to a 10-phase 4D CT of the skin
    ``ref`` (image = optical frame): the markers move anteriorly 0-12 mm with a pattern varying over
    the skin, the entry 0.9 mm and the target 0.65 mm superior-inferior per mm of score; and live
    markers mid-breath on that pattern (0.3 mm noise), so the timed steering takes the model's path,
    not a fallback."""
    rng = np.random.default_rng(seed + 1)
    pattern = np.column_stack([0.1 * rng.normal(size=len(ref)), 0.2 * rng.normal(size=len(ref)),
                               1.0 + 0.3 * rng.normal(size=len(ref))])
    target = entry + np.array([10.0, 8.0, -75.0])
    phases = tuple(PlanPhase(ref + s * pattern, target + s * np.array([0.0, -0.65, 0.1]) * 1.2,
                             entry + s * np.array([0.0, 0.1, 0.9]))
                   for s in 12.0 * np.sin(np.linspace(0.3, np.pi - 0.3, 9)) ** 2)
    plan = ProcedurePlan(ref, entry, target, "<bench>", phases)
    live = ref + 6.0 * pattern + rng.normal(0.0, 0.3, size=ref.shape)
    rows = fit_entry_pattern(plan).registered(RigidTransform.identity(), ref, entry)
    return fit_target_model(plan, 2.0, 10.0), rows, plan, live


def bench(markers: int, calls: int, seed: int) -> dict[str, dict[str, float]]:
    """Per row: ``p50_ms``, ``p99_ms``, ``max_ms`` of one call, and ``over_rigid_p50_ms``."""
    ref, live, entry = _skin(markers, seed)
    model, rows_model, plan, breathing = _model(ref, entry, seed)
    identity = RigidTransform.identity()
    tracker = TargetTracker(model)
    exposure_ns = [0]

    def steered(name: ChangeEstimator) -> None:
        exposure_ns[0] += 33_333_333                 # a pair every camera period at 30 Hz
        fit: ChangeFit | None = estimate_change(ref, breathing, entry, name, 40.0, rows_model)
        if fit is None or fit.fallback or tracker.steer(fit.T_live_from_ref, ref, breathing, plan, identity,
                                                        exposure_ns[0]).fallback:
            raise RuntimeError("the bench's breathing skin fell back: it would time the wrong path")

    def alone(name: ChangeEstimator) -> None:
        fit = estimate_change(ref, live, entry, name, 40.0, rows_model)
        if fit is None or fit.fallback:
            raise RuntimeError(f"{name} fell back on the bench's skin: it would time the wrong path")

    names: tuple[ChangeEstimator, ...] = ("rigid", "weighted", "local-tps", "pattern")
    rows: dict[str, Callable[[], None]] = {name: functools.partial(alone, name) for name in names}
    rows |= {f"{name}+surrogate": functools.partial(steered, name) for name in names}
    out: dict[str, dict[str, float]] = {}
    for name, call in rows.items():
        for _ in range(WARMUP_CALLS):
            call()
        ts = np.empty(calls)
        for i in range(calls):
            t0 = time.perf_counter_ns()
            call()
            ts[i] = (time.perf_counter_ns() - t0) * 1e-6
        out[name] = {"p50_ms": round(float(np.percentile(ts, 50)), 4),
                     "p99_ms": round(float(np.percentile(ts, 99)), 4),
                     "max_ms": round(float(ts.max()), 4)}
    for row in out.values():
        row["over_rigid_p50_ms"] = round(row["p50_ms"] - out["rigid"]["p50_ms"], 4)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench estimators", description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--markers", type=int, default=6,
                    help="skin markers (default 6, as configs/sim_patient.toml)")
    ap.add_argument("--calls", type=int, default=3000, help="timed calls per estimator (default 3000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--numpy", action="store_true",
                    help="time the numpy reference code instead of the compiled kernels")
    args = ap.parse_args(argv)
    if args.markers < 4 or args.calls < 100:
        ap.error("--markers must be >= 4 (the local spline needs 4) and --calls >= 100")
    previous = native.use_native(not args.numpy)
    try:
        res = bench(args.markers, args.calls, args.seed)
    finally:
        native.use_native(previous)
    doc = {"markers": args.markers, "calls": args.calls, "budget_over_rigid_ms": 0.2,
           "kernel": native.native_status() if not args.numpy else "numpy (--numpy)", "estimators": res}
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(f"kernel: {doc['kernel']}")
        print(f"{'estimator':<20} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'p50 over rigid':>15}")
        for name, r in res.items():
            print(f"{name:<20} {r['p50_ms']:>8.3f} {r['p99_ms']:>8.3f} {r['max_ms']:>8.3f} "
                  f"{r['over_rigid_p50_ms']:>15.3f}")
        print("budget: the pair's path may grow by 0.2 ms p99 (issue 41)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
