"""Respiratory-motion prediction on recorded breathing: every predictor of hil/prediction against
no prediction and today's COMPENSATE filter, at the system's camera rates and latencies.

Run: ``tools/bench prediction [--trace FILE ...] [--rate HZ] [--horizon-ms MS] [--noise-mm MM]
[--seed N] [--max-minutes M] [--resample cubic|linear] [--json]``

Method (docs/prediction.md): each trace (any file or paired directory the project's trace reader
takes, hil/io/traces.py) gives a target position (mm; the tumour translations, else the first
recorded skin point), which is resampled to the camera rate (``--resample``, below), Gaussian noise
like the stereo pipeline's is added (``--noise-mm``, the 3-D RMS, default 0.05 mm: the vision
bench's 3-D marker error, docs/benchmarks.md; per axis ``noise / sqrt(3)``, fixed seed), the
samples are fed one by one to a fresh predictor per trace, and after each one the prediction
``horizon`` ahead is compared with the noise-free trace (the same interpolant) at that time.
Errors are 3-D norms pooled over every sample of every trace (warm-up included: a predictor that
is not warm answers the last sample): RMS, p95, max and the RMS's ratio to no prediction.
``best`` is the predictor with the lowest RMS at the condition, ``default`` the one the controller
uses (``[procedure.compensation] predictor``'s default; chosen on the closed-loop figures too,
docs/prediction.md "In the loop").

Resampling: the shared recordings are sampled at 5 Hz, so every camera rate above it is made by
interpolating between recorded samples, and what lies between them is not known. ``cubic`` (the
default) is the C2 cubic spline through the samples (scipy ``CubicSpline``, not-a-knot ends):
breathing is smooth, and its velocity changes continuously. ``linear`` joins the samples with
straight lines: a velocity jump every 0.2 s and, at 15 Hz, two samples of every three on a straight
line, which favours the straight-line extrapolation of the alpha-beta filter (docs/prediction.md
"Resampling" has both tables and the native 5 Hz check, which needs no interpolation at all).

Without ``--trace``: the shared corpus ``<repo>/../shared/data/respiration`` (``$HIL_SHARED_DATA``
overrides ``<repo>/../shared/data``; every 6-DoF trace file and
every paired directory, its tumour part). Without ``--rate``/``--horizon-ms`` the text report is
the whole table (15, 30, 60 Hz x 33, 60, 100, 150 ms); ``--json`` reports one condition (default
15 Hz, 60 ms).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline

from hil.controller.config import CompensationConfig
from hil.errors import InputFileError
from hil.io.traces import TraceError, read_trace
from hil.prediction import PREDICTOR_NAMES, SafetyLimits, make_predictor

FloatArray = NDArray[np.float64]
REPO = Path(__file__).resolve().parents[2]
#: The shared data (data/README.md there): ``<repo>/../shared/data``, or ``$HIL_SHARED_DATA`` when
#: set (a git worktree that does not sit beside ``shared/``).
SHARED_DATA = Path(os.environ.get("HIL_SHARED_DATA") or REPO.parent / "shared" / "data")
CORPUS = SHARED_DATA / "respiration"
RATES_HZ = (15.0, 30.0, 60.0)
HORIZONS_MS = (33.0, 60.0, 100.0, 150.0)
DEFAULT_RATE_HZ = 15.0
DEFAULT_HORIZON_MS = 60.0
NOISE_MM = 0.05
#: Issue 42's targets at 15 Hz and 60 ms: RMS <= 0.5 x none and <= 0.8 x today's filter.
TARGET_RATIO_NONE = 0.5
TARGET_RATIO_FILTER = 0.8
#: ``--cost``: pairs timed per predictor, after this warm-up (s of samples: every model warm)
COST_SAMPLES = 3000
COST_WARMUP_S = 10.0


@dataclass
class Trace:
    name: str
    time_s: FloatArray  # (N,) s from the first sample
    target_mm: FloatArray  # (N, 3) mm


def load(path: Path) -> Trace:
    """A trace's target position through the project's reader (hil/io/traces.py: 6-DoF files,
    paired directories, points CSV): the tumour translations (mm), else the first recorded point.

    Raises:
        TraceError: the reader's refusal, or a trace with no 3-D position (a surrogate alone).
    """
    tr = read_trace(path)
    x = tr.target_mm if tr.target_mm is not None else next(iter(tr.points_mm.values()), None)
    if x is None:
        raise TraceError(str(path), "holds no 3-D position (a surrogate alone cannot be predicted in mm)")
    t = np.asarray(tr.time_s, dtype=np.float64)
    return Trace(path.name, t - t[0], np.asarray(x, dtype=np.float64))


def truncate(tr: Trace, max_minutes: float | None) -> Trace:
    """The trace's first ``max_minutes`` (all of it for None)."""
    if max_minutes is None:
        return tr
    keep = tr.time_s <= 60.0 * max_minutes
    return Trace(tr.name, tr.time_s[keep], tr.target_mm[keep])


def corpus_files(root: Path = CORPUS) -> list[Path]:
    """Every 6-DoF trace file and every paired directory under ``root``.

    Raises:
        InputFileError: ``root`` absent or holding no trace.
    """
    if not root.is_dir():
        raise InputFileError(str(root), "the shared respiration corpus is missing (expected beside the "
                             "repository: ../shared/data/respiration)")
    files = sorted(root.glob("interact/6dof/*/*.txt"))
    files += sorted(p for p in root.glob("interact/paired/*") if p.is_dir())
    if not files:
        raise InputFileError(str(root), "no trace files found")
    return files


#: ``--resample``: how samples between the recorded ones are made (module doc)
RESAMPLE_METHODS = ("cubic", "linear")


def resample(tr: Trace, rate_hz: float, method: str = "cubic") -> tuple[FloatArray, FloatArray]:
    """(t, x): the trace interpolated (``method``, :data:`RESAMPLE_METHODS`) at ``k / rate_hz``
    from its first to its last time."""
    t = np.arange(0.0, tr.time_s[-1] + 1e-9, 1.0 / rate_hz)
    return t, truth_at(tr, t, method)


def truth_at(tr: Trace, t: FloatArray, method: str = "cubic") -> FloatArray:
    """The trace at times ``t`` (s; clamped to the recorded span), ``method`` between its samples:
    ``cubic`` the C2 spline through them, ``linear`` straight lines (mm, (len(t), 3))."""
    if method == "linear":
        return np.stack([np.interp(t, tr.time_s, tr.target_mm[:, k]) for k in range(3)], axis=1)
    if method != "cubic":
        raise ValueError(f"--resample must be one of {', '.join(RESAMPLE_METHODS)} (got {method!r})")
    if len(tr.time_s) < 4:
        raise ValueError(f"trace {tr.name}: {len(tr.time_s)} samples, the cubic resampling needs 4")
    spline = CubicSpline(tr.time_s, tr.target_mm, axis=0)
    return np.asarray(spline(np.clip(t, tr.time_s[0], tr.time_s[-1])), dtype=float)


@dataclass
class Result:
    errors: dict[float, list[FloatArray]] = field(default_factory=dict)  # horizon_s -> per-trace errors
    fallbacks: int = 0
    seconds: float = 0.0
    samples: int = 0


def replay(traces: list[Trace], rate_hz: float, horizons_s: list[float], noise_mm: float, seed: int,
           names: tuple[str, ...] = PREDICTOR_NAMES, method: str = "cubic") -> dict[str, Result]:
    """Every predictor over every trace at ``rate_hz`` (resampled by ``method``), each horizon
    predicted after every sample."""
    cc = CompensationConfig()
    limits = SafetyLimits(max_horizon_s=max(0.2, max(horizons_s)))
    out = {n: Result({h: [] for h in horizons_s}) for n in names}
    sigma = noise_mm / math.sqrt(3.0)
    for k, tr in enumerate(traces):
        t, x = resample(tr, rate_hz, method)
        z = x + np.random.default_rng(seed + k).normal(0.0, sigma, x.shape)
        truths = {h: truth_at(tr, t + h, method) for h in horizons_s}
        valid = {h: t + h <= tr.time_s[-1] + 1e-9 for h in horizons_s}
        for name in names:
            p = make_predictor(name, rate_hz, limits, alpha=cc.filter_alpha, beta=cc.filter_beta,
                               noise_mm=sigma)
            preds = {h: np.empty_like(x) for h in horizons_s}
            t0 = time.process_time()
            for i in range(len(t)):
                p.update(float(t[i]), z[i])
                for h in horizons_s:
                    preds[h][i] = p.predict(h)
            r = out[name]
            r.seconds += time.process_time() - t0
            r.samples += len(t)
            r.fallbacks += p.fallbacks
            for h in horizons_s:
                r.errors[h].append(np.linalg.norm(preds[h][valid[h]] - truths[h][valid[h]], axis=1))
    return out


def figures(res: dict[str, Result], h: float) -> dict[str, dict[str, Any]]:
    """name -> rmse_mm, p95_mm, max_mm, ratio_to_none, fallbacks, us_per_sample (CPU, all horizons)."""
    none_rms = None
    out: dict[str, dict[str, Any]] = {}
    for name, r in res.items():
        e = np.concatenate(r.errors[h])
        rms = float(np.sqrt(np.mean(e * e)))
        if name == "none":
            none_rms = rms
        out[name] = {"rmse_mm": round(rms, 4), "p95_mm": round(float(np.percentile(e, 95)), 4),
                     "max_mm": round(float(e.max()), 4), "fallbacks": r.fallbacks,
                     "us_per_sample": round(1e6 * r.seconds / max(r.samples, 1), 1), "_rms": rms}
    for f in out.values():
        f["ratio_to_none"] = round(f.pop("_rms") / none_rms, 4) if none_rms else None
    return out


def pair_cost(rate_hz: float, samples: int = COST_SAMPLES, seed: int = 0) -> dict[str, dict[str, float]]:
    """The per-pair CPU of each predictor as COMPENSATE runs it (``--cost``): one update and the
    two predictions of the setpoint's secant (hil/controller/phases/predicted.py), timed per pair
    (wall clock, ``time.perf_counter_ns``) on simulated breathing (10 mm, 4 s, 0.05 mm noise) at
    ``rate_hz``, after a warm-up of :data:`COST_WARMUP_S` of samples. name -> p50_us, p99_us,
    max_us, mean_us (wall time: on a loaded machine it includes other processes' time) and
    cpu_mean_us (this thread's CPU per pair, the whole loop's: not inflated by preemption)."""
    rng = np.random.default_rng(seed)
    warm = round(COST_WARMUP_S * rate_hz)
    n = warm + samples
    t = np.arange(n) / rate_hz
    x = np.outer(10.0 * np.cos(np.pi * t / 4.0) ** 4, [0.0, 0.3, 1.0]) + rng.normal(0.0, 0.03, (n, 3))
    h_a, h_b = 0.09, min(0.09 + 1.0 / rate_hz, 0.15)
    out: dict[str, dict[str, float]] = {}
    for name in PREDICTOR_NAMES:
        p = make_predictor(name, rate_hz, SafetyLimits(max_horizon_s=0.15))
        us = np.empty(samples)
        cpu0 = 0
        for i in range(n):
            if i == warm:
                cpu0 = time.thread_time_ns()
            t0 = time.perf_counter_ns()
            p.update(float(t[i]), x[i])
            p.predict(h_a)
            p.predict(h_b)
            if i >= warm:
                us[i - warm] = (time.perf_counter_ns() - t0) * 1e-3
        cpu_us = (time.thread_time_ns() - cpu0) * 1e-3 / samples
        out[name] = {"cpu_mean_us": round(cpu_us, 1),"p50_us": round(float(np.percentile(us, 50)), 1),
                     "p99_us": round(float(np.percentile(us, 99)), 1),
                     "max_us": round(float(us.max()), 1), "mean_us": round(float(us.mean()), 1)}
    return out


def _best(figs: dict[str, dict[str, Any]]) -> str:
    return min(figs, key=lambda n: float(figs[n]["rmse_mm"]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench prediction", description=__doc__.split("\n")[0])
    ap.add_argument("--trace", action="append", default=[], metavar="FILE",
                    help="a trace file (repeatable); default: the shared respiration corpus")
    ap.add_argument("--rate", type=float,
                    help="camera rate, Hz (default: 15 with --json, else 15, 30 and 60)")
    ap.add_argument("--horizon-ms", type=float,
                    help="prediction horizon, ms (default: 60 with --json, else 33, 60, 100 and 150)")
    ap.add_argument("--noise-mm", type=float, default=NOISE_MM,
                    help="measurement noise, 3-D RMS, mm (default 0.05)")
    ap.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    ap.add_argument("--max-minutes", type=float,
                    help="replay only each trace's first M minutes (default: whole traces)")
    ap.add_argument("--resample", choices=RESAMPLE_METHODS, default="cubic",
                    help="how samples between the recorded ones are made: cubic spline (default) or "
                         "straight lines (module doc)")
    ap.add_argument("--json", action="store_true", help="print one JSON object (one condition)")
    ap.add_argument("--cost", action="store_true",
                    help="only the per-pair CPU of each predictor as COMPENSATE runs it (no traces)")
    args = ap.parse_args(argv)
    if args.cost:
        return _print_cost(DEFAULT_RATE_HZ if args.rate is None else args.rate, args.json)
    try:
        for v, what in ((args.rate, "--rate"), (args.horizon_ms, "--horizon-ms")):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{what} must be a number > 0 (got {v})")
        if not (math.isfinite(args.noise_mm) and args.noise_mm >= 0):
            raise ValueError(f"--noise-mm must be a number >= 0 (got {args.noise_mm})")
        if args.max_minutes is not None and not (math.isfinite(args.max_minutes) and args.max_minutes > 0):
            raise ValueError(f"--max-minutes must be a number > 0 (got {args.max_minutes})")
        if args.horizon_ms is not None and args.horizon_ms > 200:
            raise ValueError(f"--horizon-ms at most 200 ms (the predictors' bound; got {args.horizon_ms})")
        files = [Path(f) for f in args.trace] or corpus_files()
        traces = [truncate(load(f), args.max_minutes) for f in files]
        for tr in traces:
            if len(tr.time_s) < 4:
                raise ValueError(f"trace {tr.name}: {len(tr.time_s)} samples (--max-minutes "
                                 f"{args.max_minutes:g}); at least 4 are needed")
    except (ValueError, InputFileError) as exc:
        print(f"tools/bench prediction: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        rate = args.rate or DEFAULT_RATE_HZ
        h_ms = args.horizon_ms or DEFAULT_HORIZON_MS
        res = replay(traces, rate, [h_ms / 1e3], args.noise_mm, args.seed, method=args.resample)
        figs = figures(res, h_ms / 1e3)
        ab = figs["alpha-beta"]["rmse_mm"]
        best = _best(figs)
        print(json.dumps({
            "rate_hz": rate, "horizon_ms": h_ms, "noise_mm": args.noise_mm, "seed": args.seed,
            "max_minutes": args.max_minutes, "resample": args.resample,
            "traces": len(traces), "samples": res["none"].samples, "predictors": figs, "best": best,
            "default": CompensationConfig().predictor,
            "ratio_to_filter": round(figs[best]["rmse_mm"] / ab, 4) if ab else None,
            "targets": {"ratio_to_none": TARGET_RATIO_NONE, "ratio_to_filter": TARGET_RATIO_FILTER},
            "data": [str(f) for f in files] if args.trace else str(CORPUS),
        }))
        return 0
    rates = [args.rate] if args.rate else list(RATES_HZ)
    hs = [args.horizon_ms] if args.horizon_ms else list(HORIZONS_MS)
    cut = f" (first {args.max_minutes:g} min of each)" if args.max_minutes else ""
    print(f"{len(traces)} traces{cut}, resampled {args.resample}, noise {args.noise_mm:g} mm 3-D RMS "
          f"(seed {args.seed}); "
          "RMS / p95 / max error, mm, and RMS ratio to no prediction")
    print(f"{'rate':>6} {'horizon':>8}  {'predictor':<11} {'rms':>7} {'p95':>7} {'max':>7} {'/none':>6} "
          f"{'fallbacks':>9} {'us/sample':>9}")
    for rate in rates:
        res = replay(traces, rate, [h / 1e3 for h in hs], args.noise_mm, args.seed, method=args.resample)
        for h_ms in hs:
            figs = figures(res, h_ms / 1e3)
            best = _best(figs)
            for name, f in figs.items():
                mark = " *" if name == best else ""
                print(f"{rate:>4g}Hz {h_ms:>6g}ms  {name:<11} {f['rmse_mm']:>7.3f} {f['p95_mm']:>7.3f} "
                      f"{f['max_mm']:>7.3f} {f['ratio_to_none']:>6.3f} {f['fallbacks']:>9} "
                      f"{f['us_per_sample']:>9.1f}{mark}")
        sys.stdout.flush()
    print("(* lowest RMS at that condition; us/sample: CPU per sample fed, all horizons predicted)")
    return 0


def _print_cost(rate_hz: float, as_json: bool) -> int:
    """``--cost``: :func:`pair_cost` as JSON or a table; 2 on a bad rate."""
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        print(f"tools/bench prediction: error: --rate must be a number > 0 (got {rate_hz})", file=sys.stderr)
        return 2
    cost = pair_cost(rate_hz)
    if as_json:
        print(json.dumps({"rate_hz": rate_hz, "samples": COST_SAMPLES, "cost": cost,
                          "default": CompensationConfig().predictor}))
        return 0
    print(f"per-pair CPU at {rate_hz:g} Hz (update + 2 predictions, {COST_SAMPLES} pairs, wall clock, us)")
    print(f"{'predictor':<11} {'p50':>8} {'p99':>8} {'max':>8} {'mean':>8} {'CPU mean':>9}")
    for name, c in cost.items():
        print(f"{name:<11} {c['p50_us']:>8.1f} {c['p99_us']:>8.1f} {c['max_us']:>8.1f} {c['mean_us']:>8.1f} "
              f"{c['cpu_mean_us']:>9.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
