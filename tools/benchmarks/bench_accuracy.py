"""Accuracy of the whole simulated procedure over many seeds.

Run: ``tools/bench accuracy [--json] [--runs N | --rigs N [--tolerances FILE] [--executor local|dask]
[--workers W] [--scheduler ADDRESS] [--rig-timeout-s S]] [--first-seed S] [--follow-s S] [--config FILE]
[--no-rig-calibration] [--trace FILE ... [--trace-format F]] [--predictor NAME] [--estimator NAME]
[--target-model rigid|surrogate] [--ct-noise-mm X]``

Each run is ``hil run`` on the simulator (configs/sim.toml by default) with seed-001-like camera
noise (the sim camera's defaults: 1394 px, 120 mm baseline, 2 grey levels of sensor noise, blur),
breathing of 10 mm amplitude and 4 s period, and micro-motion (tremor). The real vision pipeline,
registration, gate, compensation and safety layer run in the loop; errors are measured against the
simulator's truth. Prints guide position error at lock (mean, RMS, max), direction error,
compensation error, gate open fraction and time to lock. Targets: <= 0.5 mm RMS at lock, <= 1 mm
p95 while compensating. Beside them, against the simulator's truth: the target error (the guide
axis line's closest distance to the true internal target at lock, and over the hold), the axis's
distance to the true entry, the true skin markers' rigid-fit residual (how far the body is from
rigid: 0 for the rigid phantom) and the measured rigid change's FRE over the run.

``--trace FILE`` drives the simulated patient by a recorded trace (any format of docs/traces.md;
the body becomes deformable), e.g. on ``configs/sim_patient.toml``. Given more than once, the bench
runs on each trace in turn (progress on stderr) and prints one row per trace and a summary over
them: the following p95's median, worst and how many traces are within 1 mm, the worst target at
lock and false-open rate (JSON: ``traces``, one result per trace, and ``summary``). A trace the setup
refuses (a recording without breaths for the 4D CT) is reported with its reason, the others run,
and the exit status is 2.

Two compensation figures: the normal procedure compensates during the requested breath-hold
(micro-motion only); a second run per seed (``--follow-s``, default 12 s) opens the gate at once
and follows free breathing, and its errors after a 2 s catch-up give ``comp_err_mm_p95`` (the
hold-only figure when ``--follow-s 0``). On a deformable patient the true path turns with the
target's own motion, which no skin marker shows; ``comp_entry_err_mm_p95_following`` is the part
the markers can tell (the guide axis line to the true entry while following). The ``follow_path_*``
fields split the following error further (``hil.controller.metrics.PathSample``): the path the
controller follows (its change, steered by the target model, applied to the plan) against the truth
when its pair was taken (the estimate: estimator, model, sensing) and now (plus the motion since).

With a config whose simulated rig has errors (``[simulation.rig_errors]``, e.g.
``configs/sim_realistic.toml``) every seed is run twice, side by side: with the setup as given
(the CAD flange-marker layout, no time offsets) and after ``hil rig-calibrate --auto`` of that
seed's rig (``[calibration] rig`` pointing at the file); the JSON's ``calibrated`` object holds
the second column and how far each calibration was from the simulator's truth.

``--rigs N`` (issue 43, accuracy over many rigs): N rigs drawn at random within declared tolerances
(hil/rigcal/draw.py; the defaults, or ``--tolerances FILE``; docs/bringup.md "Rig tolerances"), rig
seeds ``--first-seed`` .. ``--first-seed + N - 1``. Each rig runs the procedure with the CAD values,
is calibrated by ``hil rig-calibrate --auto``'s path, and runs again calibrated (no following run).
Prints the lock error's p50/p95/p99 across rigs, CAD and calibrated, the refused calibrations with
their reasons, and the worst rig with its draw and the command that reruns it alone
(``--rigs 1 --first-seed K``). The rigs run on the campaign executors: ``--executor local`` (this
machine, ``--workers`` rig processes at a time, default 2) or ``--executor dask`` (``--scheduler
tcp://HOST:PORT``, or a LocalCluster of ``--workers`` workers on loopback); progress on stderr.
Targets (``--rigs 50``, sim_realistic): calibrated lock error p95 <= 0.5 mm, p99 <= 0.8 mm.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from drivers.sim.planning_ct import DEFAULT_CT_NOISE_MM, four_d_ct
from hil.cli.cmd_run import run_procedure
from hil.config import SetupConfig, build_devices, default_setup_path, load_setup
from hil.config.build import clock_for
from hil.config.overrides import TRACE_FORMATS, with_trace
from hil.config.setup import target_sensor_problem
from hil.config.simulation import RigErrorsConfig
from hil.controller.change_estimate import CHANGE_ESTIMATORS
from hil.controller.config import ProcedureConfig
from hil.controller.metrics import RunSummary
from hil.controller.plan_file import ProcedurePlan, load_plan, plan_from_dict
from hil.controller.target_model import TARGET_MODELS
from hil.errors import ConfigError, HilError, InputFileError
from hil.log import configure_logging
from hil.prediction import PREDICTOR_NAMES
from hil.rigcal.collect import auto_confirm
from hil.rigcal.draw import RigTolerances, load_tolerances
from hil.rigcal.fleet import DEFAULT_RIG_TIMEOUT_S, check_simulated, open_rig_executor, rig_task, summarize
from hil.rigcal.runner import run_rig_calibration

#: The bench's breathing (every mode): 10 mm amplitude, 4 s period.
BENCH_BREATHING: dict[str, Any] = {"enabled": True, "amplitude_mm": 10.0, "period_s": 4.0}


def _rms(xs: list[float]) -> float | None:
    return float(np.sqrt(np.mean(np.square(xs)))) if xs else None


def _run_record(seed: int, s: RunSummary) -> dict[str, Any]:
    """One seed's row of ``per_run``."""
    return {"seed": seed, "final_state": s.final_state, "lock_error_mm": s.lock_error_mm,
            "lock_direction_error_deg": s.lock_direction_error_deg,
            "comp_error_p95_mm": s.comp_error_p95_mm, "gate_open_fraction": s.gate_open_fraction,
            "time_to_lock_s": s.time_to_lock_s, "fre_mm": s.fre_mm,
            "latency_ms_p95": s.latency_ms["p95"], "target_error_mm": s.target_error_mm,
            "target_error_max_mm": s.target_error_max_mm, "entry_axis_error_mm": s.entry_axis_error_mm,
            "body_rigid_residual_mm_p95": s.body_rigid_residual_mm_p95,
            "change_fre_mm_p95": s.change_fre_mm["p95"],
            "gate_false_open_rate": s.gate_false_open_rate, "gate_open_ticks": s.gate_open_ticks,
            "target_model_fallback_fraction": s.target_model_fallback_fraction,
            "target_sensor_fraction": s.target_sensor_fraction}


def _false_open(runs: list[dict[str, Any]]) -> float | None:
    """The gate's false-open rate over every run's open ticks (each run weighs by its ticks)."""
    ticks = sum(int(r["gate_open_ticks"]) for r in runs)
    false = sum(round(float(r["gate_false_open_rate"] or 0.0) * int(r["gate_open_ticks"])) for r in runs)
    return false / ticks if ticks else None


def _p95(xs: list[float]) -> float | None:
    return float(np.percentile(xs, 95)) if xs else None


def _fmt(x: float | None, unit: str = "") -> str:
    """A figure for the text tables: three decimals and its unit, or n/a."""
    return "n/a" if x is None else f"{x:.3f} {unit}".rstrip()


#: the following run's per-sample series (:func:`_follow_run`): the guide against the ideal
#: stand-off point, the guide axis line against the true entry, and the controller's path against
#: the truth (``hil.controller.metrics.PathSample``: its stand-off point when its pair was taken and
#: now, its entry, its direction in deg)
FOLLOW_SERIES = ("guide", "axis_entry", "path_pair", "path_now", "path_entry", "path_direction")


def _follow_run(cfg_path: Path, setup: SetupConfig, plan: ProcedurePlan, tmp: Path,
                follow_s: float) -> tuple[dict[str, list[float]], tuple[float, float, float | None] | None]:
    """Follow free breathing: the gate opens at once (no breath-hold asked, wide tolerance) and
    compensation runs ``follow_s`` seconds before the run is stopped; returns the truth errors after
    the first 2 s (the catch-up from the stand-off onto the moving path), by :data:`FOLLOW_SERIES`
    (NaN where the controller had no path yet), and the shares of pairs the surrogate target model
    kept the rigid direction on, steered held at a bound and pointed at the target sensor's target (None
    without a sensor; the whole None without the model)."""
    p = setup.procedure
    proc = p.model_copy(update={
        "gate": p.gate.model_copy(update={"tolerance_mm": 30.0, "hold_request_s": 0.1,
                                          "min_hold_left_s": None, "moved_after_s": None,
                                          "shape_tolerance_mm": None}),
        "compensation": p.compensation.model_copy(update={"settle_s": follow_s + 60.0}),
        "lock": p.lock.model_copy(update={"drift_alarm_mm": 30.0}),
    })
    # registration, approach and gate take about 5 s of procedure time
    s = run_procedure(cfg_path, setup.model_copy(update={"procedure": proc}), plan, auto=True,
                      session_dir=tmp, max_duration_s=6.0 + follow_s)
    late = [age > 2.0 for age in s.comp_error_age_s]
    series = (s.comp_errors_mm, s.comp_entry_errors_mm, s.comp_path_errors_mm, s.comp_path_now_errors_mm,
              s.comp_path_entry_errors_mm, s.comp_path_direction_errors_deg)
    kept = {name: [e for e, ok in zip(xs, late, strict=True) if ok]
            for name, xs in zip(FOLLOW_SERIES, series, strict=True)}
    shares = None if s.target_model_fallback_fraction is None else (
        s.target_model_fallback_fraction, s.target_model_held_fraction or 0.0, s.target_sensor_fraction)
    return kept, shares


def _with_4d_ct(plan: ProcedurePlan, setup: SetupConfig,
                ct_noise_mm: float = DEFAULT_CT_NOISE_MM) -> ProcedurePlan:
    """``plan`` with this seed's simulated 4D CT (drivers/sim/planning_ct.py; localisation error
    ``ct_noise_mm`` per axis in every phase) when the surrogate target model or the pattern
    estimator needs one and the plan has none; else ``plan``.

    Raises:
        InputFileError: the simulated patient cannot give a 4D CT (a rigid phantom, a trace with
            too few breaths before the start), naming the plan.
    """
    c = setup.procedure.compensation
    if (c.target_model != "surrogate" and c.estimator != "pattern") or plan.phases:
        return plan
    try:
        ct = four_d_ct(setup.simulation, noise_mm=ct_noise_mm)
    except ValueError as exc:
        raise InputFileError(plan.source, f"no phases for the surrogate target model or the pattern "
                                          f"estimator, and {exc}") from None
    doc = {"format": "hil-plan", "version": 1, "fiducials_mm": plan.fiducials_mm.tolist(),
           "entry_mm": plan.entry_mm.tolist(), "target_mm": plan.target_mm.tolist(), "phases": ct.phases,
           "phases_period_s": ct.period_s}
    return plan_from_dict(doc, f"{plan.source} + simulated 4D CT (seed {setup.simulation.seed})")


def _calibrate_rig(cfg_path: Path, setup: SetupConfig, out: Path) -> dict[str, Any]:
    """``hil rig-calibrate --auto`` of this seed's simulated rig into ``out``; its summary."""
    clock = clock_for(setup)
    outcome = run_rig_calibration(setup, cfg_path, build_devices(setup, clock), clock, auto_confirm,
                                  out_path=out)
    return outcome.summary


def _column(runs: list[dict[str, Any]], comp_all: list[float], hold_targets: list[float],
            follow: dict[str, list[float]], follow_model: list[tuple[float, float, float | None]],
            hold_entries: list[float]) -> dict[str, Any]:
    """One column's figures from its seeds' records and the pooled samples (mm, deg, s; None where
    no run gave the figure). The compensation p95 is the following run's where one was made;
    ``follow_model``: each following run's target model shares (fell back, held at a bound, by the
    target sensor or None);
    ``hold_targets`` / ``hold_entries``: every LOCK sample's axis to the true target / entry."""
    follow_all = follow["guide"]
    comp_main = follow_all or comp_all
    locked = [r for r in runs if r["lock_error_mm"] is not None]
    lock = [float(r["lock_error_mm"]) for r in locked]
    dirs = [float(r["lock_direction_error_deg"]) for r in locked]
    ttl = [float(r["time_to_lock_s"]) for r in runs if r["time_to_lock_s"] is not None]
    gates = [float(r["gate_open_fraction"]) for r in runs if r["gate_open_fraction"] is not None]
    targets = [float(r["target_error_mm"]) for r in locked if r["target_error_mm"] is not None]
    entries = [float(r["entry_axis_error_mm"]) for r in locked if r["entry_axis_error_mm"] is not None]
    residuals = [float(r["body_rigid_residual_mm_p95"]) for r in runs
                 if r["body_rigid_residual_mm_p95"] is not None]
    fres = [float(r["change_fre_mm_p95"]) for r in runs if r["change_fre_mm_p95"] is not None]
    return {
        "runs": len(runs),
        "runs_done": sum(r["final_state"] == "done" for r in runs),
        "lock_err_mm_mean": statistics.fmean(lock) if lock else None,
        "lock_err_mm_rms": _rms(lock),
        "lock_err_mm_max": max(lock) if lock else None,
        "dir_err_deg_rms": _rms(dirs),
        "comp_err_mm_p95": float(np.percentile(comp_main, 95)) if comp_main else None,
        "comp_err_mm_rms_following": _rms(follow_all),
        **_following_per_seed(runs),
        "comp_entry_err_mm_p95_following": _p95(follow["axis_entry"]),
        **_following_split(follow),
        "target_model_fallback_fraction_following": statistics.fmean(f for f, *_ in follow_model)
        if follow_model else None,
        "target_model_held_fraction_following": statistics.fmean(h for _, h, _ in follow_model)
        if follow_model else None,
        "target_sensor_fraction_following": statistics.fmean(f for *_, f in follow_model if f is not None)
        if any(f is not None for *_, f in follow_model) else None,
        "comp_err_mm_rms_hold": _rms(comp_all),
        "comp_err_mm_p95_hold": float(np.percentile(comp_all, 95)) if comp_all else None,
        "target_err_mm_rms": _rms(targets),
        "target_err_mm_p95": _p95(targets),
        "target_err_mm_max": max(targets) if targets else None,
        "target_err_hold_mm_p95": _p95(hold_targets),
        "entry_axis_err_mm_rms": _rms(entries),
        "entry_axis_err_hold_mm_rms": _rms(hold_entries),
        "body_rigid_residual_mm_p95": _p95(residuals),
        "change_fre_mm_p95": _p95(fres),
        "gate_false_open_rate": _false_open(runs),
        "gate_open_fraction_mean": statistics.fmean(gates) if gates else None,
        "time_to_lock_s_median": statistics.median(ttl) if ttl else None,
        "per_run": runs,
    }


def _following_per_seed(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The following error seed by seed (mm): each seed's own p95 (``follow_guide_mm_p95`` of its
    ``per_run`` record), their median, the worst and its seed, and how many are over 1 mm. The
    pooled p95 (``comp_err_mm_p95``) is one figure over every seed's samples; a seed whose
    following is poor can sit under it (docs/benchmarks.md, issue 41, sixteenth session). None
    (0 seeds over) without a following run."""
    own = [(float(r["follow_guide_mm_p95"]), int(r["seed"])) for r in runs
           if r.get("follow_guide_mm_p95") is not None]
    worst = max(own) if own else None
    return {"follow_guide_mm_p95_seed_median": statistics.median(p for p, _ in own) if own else None,
            "follow_guide_mm_p95_seed_max": None if worst is None else worst[0],
            "follow_guide_mm_p95_worst_seed": None if worst is None else worst[1],
            "follow_guide_seeds_over_1mm": sum(p > 1.0 for p, _ in own)}


def _following_split(follow: dict[str, list[float]]) -> dict[str, Any]:
    """Where the following error comes from (docs/benchmarks.md, issue 41): the controller's path
    against the truth, p95 (mm, deg) over the samples that had a path: its stand-off point when
    its pair was taken (the estimate: estimator, target model, sensing) and now (plus the body's
    motion since the pair), its entry and its direction when its pair was taken."""
    def finite(name: str) -> list[float]:
        return [x for x in follow[name] if np.isfinite(x)]
    return {"follow_path_pair_mm_p95": _p95(finite("path_pair")),
            "follow_path_now_mm_p95": _p95(finite("path_now")),
            "follow_path_entry_mm_p95": _p95(finite("path_entry")),
            "follow_path_direction_deg_p95": _p95(finite("path_direction"))}


def _bench(cfg_path: Path, base: SetupConfig, plan: ProcedurePlan, args: argparse.Namespace, tmp: Path,
           calibrate: bool) -> dict[str, Any]:
    """One column of the table: every seed with the setup as given (CAD layout, no time offsets)
    or, with ``calibrate``, after ``hil rig-calibrate`` of that seed's rig (``[calibration] rig``)."""
    breathing = base.simulation.breathing.model_copy(update=BENCH_BREATHING)
    runs: list[dict[str, Any]] = []
    comp_all: list[float] = []
    follow: dict[str, list[float]] = {name: [] for name in FOLLOW_SERIES}
    hold_targets: list[float] = []
    hold_entries: list[float] = []
    follow_model: list[tuple[float, float, float | None]] = []
    rig_errors: list[dict[str, Any]] = []
    for k in range(args.runs):
        seed = args.first_seed + k
        sim = base.simulation.model_copy(update={"seed": seed, "breathing": breathing})
        setup = base.model_copy(update={"simulation": sim})
        seed_plan = _with_4d_ct(plan, setup, args.ct_noise_mm)
        if calibrate:
            rig_path = tmp / f"rig_{seed}.json"
            rc = _calibrate_rig(cfg_path, setup, rig_path)
            rig_errors.append({"seed": seed, "layout_mm_rms": rc.get("truth_layout_error_mm_rms"),
                               "time_offset_error_ms": rc.get("truth_time_offset_error_ms")})
            cal = setup.calibration.model_copy(update={"rig": rig_path})
            setup = setup.model_copy(update={"calibration": cal})
        s = run_procedure(cfg_path, setup, seed_plan, auto=True, session_dir=tmp)
        comp_all += s.comp_errors_mm
        hold_targets += s.lock_target_errors_mm
        hold_entries += s.lock_entry_errors_mm
        record = _run_record(seed, s)
        if args.follow_s > 0:
            got, shares = _follow_run(cfg_path, setup, seed_plan, tmp, args.follow_s)
            for name in FOLLOW_SERIES:
                follow[name] += got[name]
            if shares is not None:
                follow_model.append(shares)
            record["follow_guide_mm_p95"] = _p95(got["guide"])
        runs.append(record)
        if not args.json:
            print(f"{'calibrated' if calibrate else 'as given'} seed {seed}: {s.final_state}, "
                  f"lock {s.lock_error_mm}, dir {s.lock_direction_error_deg}", file=sys.stderr)
    out = _column(runs, comp_all, hold_targets, follow, follow_model, hold_entries)
    if calibrate:
        layout = [float(r["layout_mm_rms"]) for r in rig_errors if r["layout_mm_rms"] is not None]
        offs = [abs(float(e)) for r in rig_errors for e in (r["time_offset_error_ms"] or {}).values()]
        out["rig_layout_error_mm_rms_max"] = max(layout) if layout else None
        out["rig_time_offset_error_ms_max"] = max(offs) if offs else None
        out["rig_per_seed"] = rig_errors
    return out


def rerun_command(cfg_path: Path, plan: str | None, tolerances: str | None, seed: int) -> str:
    """The command that reruns rig ``seed`` alone (``plan``, ``tolerances``: as given, or None)."""
    return (f"tools/bench accuracy --config {cfg_path}" + (f" --plan {plan}" if plan else "")
            + f" --rigs 1 --first-seed {seed}" + (f" --tolerances {tolerances}" if tolerances else "")
            + " --json")


def bench_rigs(cfg_path: Path, plan_path: Path, tolerances: RigTolerances,
               args: argparse.Namespace) -> dict[str, Any]:
    """``--rigs N``: the rigs on the chosen executor; the summary over rigs (hil/rigcal/fleet.py).
    Progress on stderr, one line per finished rig. Blocking.

    Raises:
        ExecutorError: the executor cannot be used (one line).
    """
    seeds = [args.first_seed + k for k in range(args.rigs)]
    rerun = {k: rerun_command(cfg_path, args.plan, args.tolerances, k) for k in seeds}
    tasks = [rig_task(cfg_path, plan_path, tolerances, k, replay=rerun[k], timeout_s=args.rig_timeout_s,
                      breathing=BENCH_BREATHING) for k in seeds]
    t0, done = time.perf_counter(), [0]

    def progress(line: str) -> None:
        done[0] += "running it once more" not in line
        print(f"[{done[0]}/{len(tasks)} {time.perf_counter() - t0:.0f} s] {line}", file=sys.stderr,
              flush=True)

    with open_rig_executor(args.executor, workers=args.workers, scheduler=args.scheduler) as ex:
        records = ex.run(tasks, progress=progress)
        where = ex.description
    out = summarize(records, rerun)
    out["executor"] = where
    out["tolerances"] = tolerances.model_dump(mode="json")
    return out


def _print_rigs(out: dict[str, Any]) -> None:
    def f(x: float | None) -> str:
        return _fmt(x, "mm")
    print(f"rigs: {out['rigs']} ({out['executor']['kind']}, {out['executor']['workers']} workers)")
    print(f"{'lock error over rigs':24}{'p50':>12}{'p95':>12}{'p99':>12}{'max':>12}{'locked':>8}{'done':>6}")
    for col in ("cad", "calibrated"):
        cells = "".join(f"{f(out[f'lock_err_mm_{q}_{col}']):>12}" for q in ("p50", "p95", "p99", "max"))
        print(f"{col:24}{cells}{out[f'locked_{col}']:>8}{out[f'done_{col}']:>6}")
    print(f"refused calibrations: {out['refused']}"
          + "".join(f"\n  {n} x {why}" for why, n in out["refused_reasons"].items()))
    print(f"rigs without figures (crash, hang): {out['crashed']}"
          + "".join(f"\n  {n} x {why}" for why, n in out["crashed_reasons"].items()))
    w = out["worst"]
    if w is not None:
        print(f"worst rig: seed {w['seed']}, lock error calibrated {f(w['lock_err_mm_calibrated'])}, "
              f"CAD {f(w['lock_err_mm_cad'])}\n  draw: {json.dumps(w['draw'])}\n  rerun: {w['rerun']}")
    print("targets (--rigs 50): calibrated lock error p95 <= 0.5 mm, p99 <= 0.8 mm")


def _per_seed_row(o: dict[str, Any]) -> str:
    """The seeds' own following p95: median / worst (its seed), or n/a."""
    if o["follow_guide_mm_p95_seed_max"] is None:
        return "n/a"
    return (f"{o['follow_guide_mm_p95_seed_median']:.2f}/{o['follow_guide_mm_p95_seed_max']:.2f}"
            f" (s{o['follow_guide_mm_p95_worst_seed']})")


def _print(cols: dict[str, dict[str, Any]]) -> None:
    f = _fmt
    rows: list[tuple[str, Callable[[dict[str, Any]], str]]] = [
            ("runs reaching done", lambda o: f"{o['runs_done']}/{o['runs']}"),
            ("lock error RMS", lambda o: f(o["lock_err_mm_rms"], "mm")),
            ("lock error mean", lambda o: f(o["lock_err_mm_mean"], "mm")),
            ("lock error max", lambda o: f(o["lock_err_mm_max"], "mm")),
            ("direction error RMS", lambda o: f(o["dir_err_deg_rms"], "deg")),
            ("comp. following p95", lambda o: f(o["comp_err_mm_p95"], "mm")),
            ("comp. following RMS", lambda o: f(o["comp_err_mm_rms_following"], "mm")),
            ("follow p95 seed med/max", _per_seed_row),
            ("axis to entry, follow p95", lambda o: f(o["comp_entry_err_mm_p95_following"], "mm")),
            ("path at its pair p95", lambda o: f(o["follow_path_pair_mm_p95"], "mm")),
            ("path now p95", lambda o: f(o["follow_path_now_mm_p95"], "mm")),
            ("path entry at pair p95", lambda o: f(o["follow_path_entry_mm_p95"], "mm")),
            ("path dir. at pair p95", lambda o: f(o["follow_path_direction_deg_p95"], "deg")),
            ("comp. breath-hold p95", lambda o: f(o["comp_err_mm_p95_hold"], "mm")),
            ("target error RMS", lambda o: f(o["target_err_mm_rms"], "mm")),
            ("target error p95", lambda o: f(o["target_err_mm_p95"], "mm")),
            ("target over hold p95", lambda o: f(o["target_err_hold_mm_p95"], "mm")),
            ("axis to entry RMS", lambda o: f(o["entry_axis_err_mm_rms"], "mm")),
            ("axis to entry, hold RMS", lambda o: f(o["entry_axis_err_hold_mm_rms"], "mm")),
            ("body residual p95", lambda o: f(o["body_rigid_residual_mm_p95"], "mm")),
            ("change FRE p95", lambda o: f(o["change_fre_mm_p95"], "mm")),
            ("gate false-open rate", lambda o: f(o["gate_false_open_rate"], "")),
            ("gate open fraction", lambda o: f(o["gate_open_fraction_mean"], "")),
            ("time to lock median", lambda o: f(o["time_to_lock_s_median"], "s"))]
    names = list(cols)
    print(f"{'':24}" + "".join(f"{n:>22}" for n in names))
    for label, get in rows:
        print(f"{label:24}" + "".join(f"{get(cols[n]):>22}" for n in names))
    cal = cols.get("calibrated rig")
    if cal is not None:
        print(f"rig calibration vs truth: layout <= {f(cal['rig_layout_error_mm_rms_max'], 'mm RMS')}, "
              f"time offsets <= {f(cal['rig_time_offset_error_ms_max'], 'ms')} (worst seed)")
    print("targets (calibrated rig): lock error <= 0.5 mm RMS, following free breathing <= 1 mm p95")


def _parser() -> argparse.ArgumentParser:
    """The bench's command line (module doc)."""
    ap = argparse.ArgumentParser(prog="tools/bench accuracy", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="number of seeds (default 5)")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--config", help="setup TOML (default: configs/sim.toml)")
    ap.add_argument("--plan", help="plan JSON (default: plans/<config>_plan.json)")
    ap.add_argument("--follow-s", type=float, default=12.0,
                    help="per seed, also follow free breathing for this long (0: skip)")
    ap.add_argument("--no-rig-calibration", action="store_true",
                    help="with [simulation.rig_errors] set: skip the calibrated-rig column")
    ap.add_argument("--calibrated-only", action="store_true",
                    help="with [simulation.rig_errors] set: only the calibrated-rig column (at top level)")
    ap.add_argument("--trace", metavar="FILE", action="append",
                    help="drive the simulated patient by this recorded trace (docs/traces.md; the body "
                         "becomes deformable); given more than once, the bench runs on each trace in "
                         "turn and adds a summary over them")
    ap.add_argument("--trace-format", default="auto", choices=TRACE_FORMATS,
                    help="the trace's format (default: told from the file)")
    ap.add_argument("--estimator", choices=CHANGE_ESTIMATORS,
                    help="override [procedure.compensation] estimator for this run (docs/compensation.md)")
    ap.add_argument("--rigs", type=int, metavar="N",
                    help="N rigs drawn within tolerances, each CAD and calibrated (seeds --first-seed ..)")
    ap.add_argument("--tolerances", metavar="FILE",
                    help="with --rigs: the rig tolerances (TOML; default: hil/rigcal/draw.py's; "
                         "docs/bringup.md)")
    ap.add_argument("--executor", choices=["local", "dask"], default="local",
                    help="with --rigs: where the rigs run (default: local processes)")
    ap.add_argument("--workers", type=int, default=2,
                    help="with --rigs: rigs at a time (local), or LocalCluster workers (dask); default 2")
    ap.add_argument("--scheduler", metavar="ADDRESS",
                    help="with --executor dask: the Dask scheduler (tcp://host:8786); default a LocalCluster")
    ap.add_argument("--rig-timeout-s", type=float, default=DEFAULT_RIG_TIMEOUT_S,
                    help=f"with --rigs: wall-time bound of one rig (default {DEFAULT_RIG_TIMEOUT_S:g} s)")
    ap.add_argument("--predictor", choices=PREDICTOR_NAMES,
                    help="override [procedure.compensation] predictor for this run (docs/prediction.md)")
    ap.add_argument("--ct-noise-mm", type=float, default=DEFAULT_CT_NOISE_MM,
                    help="the simulated 4D CT's localisation error per axis in every phase, mm (default "
                         f"{DEFAULT_CT_NOISE_MM}; used where a seed gets its simulated 4D CT)")
    ap.add_argument("--target-model", choices=TARGET_MODELS,
                    help="override [procedure.compensation] target_model for this run "
                         "(docs/compensation.md); surrogate with a plan without phases uses each seed's "
                         "simulated 4D CT")
    ap.add_argument("--target-sensor", metavar="NAME",
                    help="override [procedure.tracking] target_sensor for this run: the path points at the "
                         "target this tracker sensor measures, the surrogate model when it has none "
                         "(docs/compensation.md \"A sensor at the target\"; needs the surrogate model)")
    ap.add_argument("--json", action="store_true", help="one JSON object on stdout")
    return ap


def _with_compensation(setup: SetupConfig, **update: str) -> SetupConfig:
    """``setup`` with ``[procedure.compensation]`` keys overridden (``--estimator``, ``--predictor``)."""
    comp = setup.procedure.compensation.model_copy(update=update)
    return setup.model_copy(update={"procedure": setup.procedure.model_copy(update={"compensation": comp})})


def _with_target_sensor(setup: SetupConfig, name: str) -> SetupConfig:
    """``setup`` with ``[procedure.tracking] target_sensor = name`` (``--target-sensor``), checked as
    the setup file's would be.

    Raises:
        ConfigError: the procedure or the setup refuses it (no surrogate model, no such sensor)."""
    p = setup.procedure
    tracking = p.tracking.model_copy(update={"target_sensor": name})
    try:
        proc = ProcedureConfig.model_validate(p.model_copy(update={"tracking": tracking}).model_dump())
    except ValidationError as exc:
        raise ConfigError("--target-sensor", [e["msg"] for e in exc.errors()]) from None
    out = setup.model_copy(update={"procedure": proc})
    why = target_sensor_problem(out)
    if why is not None:
        raise ConfigError("--target-sensor", [why])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error("--runs must be >= 1")
    if not 0.0 <= args.ct_noise_mm < 10.0:
        ap.error("--ct-noise-mm must be >= 0 and < 10 mm")
    if args.rigs is not None:
        return _main_rigs(ap, args)
    configure_logging(level="error")
    cfg_path = Path(args.config) if args.config else default_setup_path()
    traces: list[str] = args.trace or []
    if len(traces) > 1:
        return _main_traces(cfg_path, traces, args)
    try:
        out = _one_setup(cfg_path, traces[0] if traces else None, args)
    except HilError as exc:   # the setup, the plan, or what only opening the devices finds
        print(f"tools/bench accuracy: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("tools/bench accuracy: interrupted", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(out))
    else:
        _print(_columns(out))
    return 0


def _one_setup(cfg_path: Path, trace: str | None, args: argparse.Namespace) -> dict[str, Any]:
    """The bench on the config (driven by ``trace`` when given): its column(s) and what ran.

    Raises:
        HilError: the setup, the plan or the trace refused (a surrogate model the setup cannot
            feed is refused here, not per seed), or what only opening the devices finds (a
            calibration file).
    """
    base = load_setup(cfg_path)
    if trace:
        base = with_trace(base, trace, args.trace_format)
    overrides = {k: v for k, v in (("estimator", args.estimator), ("predictor", args.predictor),
                                   ("target_model", args.target_model)) if v}
    if overrides:
        base = _with_compensation(base, **overrides)
    if args.target_sensor:
        base = _with_target_sensor(base, args.target_sensor)
    bundled = cfg_path.resolve().parent / "plans" / f"{cfg_path.stem}_plan.json"
    plan = load_plan(Path(args.plan) if args.plan else bundled)
    _with_4d_ct(plan, base)
    side_by_side = base.simulation.rig_errors != RigErrorsConfig() and not args.no_rig_calibration
    t0 = time.perf_counter()
    only_calibrated = side_by_side and args.calibrated_only
    with tempfile.TemporaryDirectory(prefix="bench_accuracy_") as tmp:
        out = _bench(cfg_path, base, plan, args, Path(tmp), calibrate=only_calibrated)
        if side_by_side and not only_calibrated:
            out["calibrated"] = _bench(cfg_path, base, plan, args, Path(tmp), calibrate=True)
    out["column"] = ("calibrated rig" if only_calibrated else "as configured (CAD)" if side_by_side
                     else "as configured")
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    out["config"] = str(cfg_path)
    out["trace"] = trace
    out["estimator"] = base.procedure.compensation.estimator
    out["predictor"] = base.procedure.compensation.predictor
    out["target_model"] = base.procedure.compensation.target_model
    out["target_sensor"] = base.procedure.tracking.target_sensor
    out["ct_noise_mm"] = args.ct_noise_mm
    return out


def _columns(out: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The text table's columns of one setup's result: the first, and the calibrated one beside it."""
    cols = {str(out["column"]): out}
    if "calibrated" in out:
        cols["calibrated rig"] = out["calibrated"]
    return cols


def _main_traces(cfg_path: Path, traces: list[str], args: argparse.Namespace) -> int:
    """``--trace`` more than once: the bench on each trace in turn (progress on stderr), each
    trace's result under ``traces`` and a summary over them (:func:`_trace_summary`). A trace the
    setup refuses (no breaths for a 4D CT, a file that cannot be read) is reported with its reason
    and the others still run; the exit status is then 2."""
    results: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i, trace in enumerate(traces, 1):
        try:
            out = _one_setup(cfg_path, trace, args)
        except HilError as exc:
            results.append({"trace": trace, "error": str(exc)})
            print(f"trace {i}/{len(traces)} {_trace_name(trace)}: error: {exc}", file=sys.stderr)
            continue
        except KeyboardInterrupt:
            print("tools/bench accuracy: interrupted", file=sys.stderr)
            return 130
        results.append(out)
        print(f"trace {i}/{len(traces)} {_trace_name(trace)}: following p95 "
              f"{_fmt(_judged(out)['comp_err_mm_p95'])} mm ({out['wall_s']} s)", file=sys.stderr)
    summary = _trace_summary(results)
    if args.json:
        print(json.dumps({"traces": results, "summary": summary, "config": str(cfg_path),
                          "wall_s": round(time.perf_counter() - t0, 1)}))
    else:
        _print_traces(results, summary)
    return 2 if summary["failed"] else 0


def _judged(out: dict[str, Any]) -> dict[str, Any]:
    """The column a setup's result is judged by: the calibrated rig's when there is one."""
    cal: dict[str, Any] | None = out.get("calibrated")
    return out if cal is None else cal


def _trace_name(trace: str) -> str:
    """A trace's short name: its file's or its directory's (a paired trace is a directory)."""
    return Path(trace).stem or trace


def _trace_summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Over the traces that ran (each judged by :func:`_judged`): the following p95's median, the
    worst and its trace, how many are within 1 mm (the issue's figure); the worst of the axis to
    the entry while following, the lock error RMS, the target at lock p95 and the false-open rate;
    and the traces refused, with their reasons (mm; None where no trace gave the figure)."""
    ran = [(str(r["trace"]), _judged(r)) for r in results if "error" not in r]

    def worst(key: str) -> float | None:
        got = [float(c[key]) for _, c in ran if c.get(key) is not None]
        return max(got) if got else None
    follow = [(float(c["comp_err_mm_p95"]), t) for t, c in ran if c.get("comp_err_mm_p95") is not None]
    top = max(follow) if follow else None
    return {"traces": len(results), "ran": len(ran),
            "failed": [{"trace": r["trace"], "error": r["error"]} for r in results if "error" in r],
            "comp_err_mm_p95_median": statistics.median(p for p, _ in follow) if follow else None,
            "comp_err_mm_p95_max": None if top is None else top[0],
            "comp_err_mm_p95_worst_trace": None if top is None else top[1],
            "traces_within_1mm": sum(p <= 1.0 for p, _ in follow),
            "comp_entry_err_mm_p95_following_max": worst("comp_entry_err_mm_p95_following"),
            "lock_err_mm_rms_max": worst("lock_err_mm_rms"),
            "target_err_mm_p95_max": worst("target_err_mm_p95"),
            "gate_false_open_rate_max": worst("gate_false_open_rate")}


def _print_traces(results: list[dict[str, Any]], summary: dict[str, Any]) -> None:
    """One row per trace (mm, deg) and the summary; a refused trace's row gives its reason."""
    heads = ("following p95", "axis-entry p95", "path dir. p95", "lock RMS", "target p95", "false-open")
    keys = ("comp_err_mm_p95", "comp_entry_err_mm_p95_following", "follow_path_direction_deg_p95",
            "lock_err_mm_rms", "target_err_mm_p95", "gate_false_open_rate")
    print(f"{'trace':34}" + "".join(f"{h:>15}" for h in heads))
    for r in results:
        name = _trace_name(str(r["trace"]))[:33]
        if "error" in r:
            print(f"{name:34}  error: {r['error']}")
            continue
        col = _judged(r)
        print(f"{name:34}" + "".join(f"{_fmt(col.get(k)):>15}" for k in keys))
    s = summary
    top = s["comp_err_mm_p95_worst_trace"]
    print(f"following p95 over {s['ran']} traces: median {_fmt(s['comp_err_mm_p95_median'])} mm, worst "
          f"{_fmt(s['comp_err_mm_p95_max'])} mm" + (f" ({_trace_name(top)})" if top else "")
          + f", within 1 mm on {s['traces_within_1mm']} of {s['ran']}")
    print(f"worst: axis to entry while following {_fmt(s['comp_entry_err_mm_p95_following_max'])} mm p95, "
          f"lock {_fmt(s['lock_err_mm_rms_max'])} mm RMS, target at lock "
          f"{_fmt(s['target_err_mm_p95_max'])} mm p95, false-open rate {_fmt(s['gate_false_open_rate_max'])}")
    if s["failed"]:
        print(f"{len(s['failed'])} trace(s) refused (above); the figures are over the others")
    print("targets (issue 41): following <= 1 mm p95 on every trace, target at lock <= 1.5 mm p95, "
          "false-open rate <= 0.01")


def _main_rigs(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """``--rigs N``: the many-rigs bench (module doc)."""
    if args.rigs < 1:
        ap.error("--rigs must be >= 1")
    if args.workers < 1:
        ap.error("--workers must be >= 1")
    if args.first_seed < 0:
        ap.error("--first-seed must be >= 0 with --rigs")
    if args.trace or args.estimator or args.target_model or args.calibrated_only or args.no_rig_calibration:
        ap.error("--rigs runs every rig CAD and calibrated on the config as given: no --trace, --estimator, "
                 "--target-model, --calibrated-only, --no-rig-calibration")
    configure_logging(level="error")
    cfg_path = Path(args.config) if args.config else default_setup_path()
    bundled = cfg_path.resolve().parent / "plans" / f"{cfg_path.stem}_plan.json"
    plan_path = Path(args.plan) if args.plan else bundled
    t0 = time.perf_counter()
    try:
        load_plan(plan_path)
        check_simulated(load_setup(cfg_path), cfg_path)
        tolerances = load_tolerances(Path(args.tolerances)) if args.tolerances else RigTolerances()
        out = bench_rigs(cfg_path, plan_path, tolerances, args)
    except HilError as exc:
        print(f"tools/bench accuracy: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("tools/bench accuracy: interrupted (the running rigs were stopped)", file=sys.stderr)
        return 130
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    out["config"] = str(cfg_path)
    if args.json:
        print(json.dumps(out))
    else:
        _print_rigs(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
