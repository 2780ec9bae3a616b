"""The entry's error of each change estimator on the simulated deformable body with the skin
markers' true positions: what each model can do with perfect sensing (issue 41).

Run: ``tools/bench entry [--json] [--config FILE] [--seeds N] [--first-seed S] [--seconds S]``

Each seed: the body of CONFIG's ``[simulation]`` (configs/sim_patient.toml by default) with
``tools/bench accuracy``'s breathing (10 mm, 4 s), its planning 4D CT (drivers/sim/planning_ct.py:
10 phases, 0.3 mm localisation error, the entry at every phase) and free breathing from 5 s on for
``--seconds`` (default 55), sampled at 15 Hz. No camera, no rig, no registration: the skin
markers and the entry are the body's own (image frame), the reference is the body at rest (the
registered end-exhale). For every estimator (``[procedure.compensation] weight_sigma_mm`` of
CONFIG; ``pattern`` fitted to the seed's 4D CT), the change applied to the registered entry against
the body's entry, mm: p50 / p95 / max over every sample of every seed. The loop's own split of
the following error is ``tools/bench accuracy``'s ``follow_path_*`` (docs/benchmarks.md, tenth
session).

Exit 0 with the table (or ``--json``); exit 2 with one line for bad input (an unreadable config, a
rigid phantom, a body driven by a trace).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.body import model_body
from drivers.sim.motion import PatientMotion
from drivers.sim.planning_ct import four_d_ct_plan
from drivers.sim.world import phantom_from_config
from hil.config import load_setup
from hil.controller.change_estimate import ChangeEstimator, estimate_change
from hil.controller.entry_pattern import fit_entry_pattern
from hil.controller.plan_file import plan_from_dict
from hil.errors import HilError
from hil.geometry.transform import RigidTransform
from hil.log import configure_logging

#: ``tools/bench accuracy``'s breathing
BENCH_BREATHING: dict[str, Any] = {"enabled": True, "amplitude_mm": 10.0, "period_s": 4.0}
ESTIMATORS: tuple[ChangeEstimator, ...] = ("rigid", "weighted", "local-tps", "pattern")
SAMPLE_HZ = 15.0
START_S = 5.0


def seed_errors(cfg_path: Path, seed: int, seconds: float) -> dict[str, list[float]]:
    """One seed's entry errors (mm) per estimator, every sample.

    Raises:
        HilError: an unreadable config.
        ValueError: a body that has no 4D CT (a rigid phantom, a trace).
    """
    setup = load_setup(cfg_path)
    sim = setup.simulation.model_copy(update={
        "seed": seed, "breathing": setup.simulation.breathing.model_copy(update=BENCH_BREATHING)})
    plan = plan_from_dict(four_d_ct_plan(sim), f"4D CT of seed {seed}")
    phantom = phantom_from_config(sim.patient)
    body = model_body(sim, phantom, PatientMotion(sim))
    ref = np.asarray(phantom.markers_mm, dtype=np.float64)
    entry = np.asarray(phantom.entry_mm, dtype=np.float64)
    comp = setup.procedure.compensation
    rows = fit_entry_pattern(plan).registered(RigidTransform.identity(), ref, entry, comp.pattern_residual_mm)
    out: dict[str, list[float]] = {name: [] for name in ESTIMATORS}
    for t in np.arange(START_S, START_S + seconds, 1.0 / SAMPLE_HZ):
        state = body.state(float(t))
        for name in ESTIMATORS:
            fit = estimate_change(ref, state.markers_mm, entry, name, comp.weight_sigma_mm, rows)
            if fit is not None:
                out[name].append(float(np.linalg.norm(fit.T_live_from_ref.apply(entry) - state.entry_mm)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench entry", description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--config", default="configs/sim_patient.toml", help="the simulated patient's setup")
    ap.add_argument("--seeds", type=int, default=12, help="seeds (default 12)")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=55.0, help="free breathing per seed, s (default 55)")
    args = ap.parse_args(argv)
    if args.seeds < 1 or not args.seconds > 0:
        ap.error("--seeds must be >= 1 and --seconds > 0")
    configure_logging(level="error")
    t0 = time.perf_counter()
    pooled: dict[str, list[float]] = {name: [] for name in ESTIMATORS}
    try:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            for name, errs in seed_errors(Path(args.config), seed, args.seconds).items():
                pooled[name] += errs
    except (HilError, ValueError) as exc:
        print(f"tools/bench entry: error: {exc}", file=sys.stderr)
        return 2
    table = {name: {"samples": len(e), "p50_mm": round(float(np.percentile(e, 50)), 3),
                    "p95_mm": round(float(np.percentile(e, 95)), 3), "max_mm": round(float(max(e)), 3)}
             for name, e in pooled.items() if e}
    if args.json:
        print(json.dumps({"config": args.config, "seeds": args.seeds, "first_seed": args.first_seed,
                          "seconds": args.seconds, "estimators": table,
                          "wall_s": round(time.perf_counter() - t0, 1)}))
        return 0
    last = args.first_seed + args.seeds - 1
    print(f"the entry with the markers' true positions, seeds {args.first_seed}-{last}, "
          f"{args.seconds:g} s each ({args.config})")
    print(f"{'estimator':12}{'p50 mm':>10}{'p95 mm':>10}{'max mm':>10}{'samples':>10}")
    for name, row in table.items():
        print(f"{name:12}{row['p50_mm']:>10.3f}{row['p95_mm']:>10.3f}{row['max_mm']:>10.3f}{row['samples']:>10}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
