"""The simulated patient's own statistics beside the recorded ones, and what the body costs.

Run: ``tools/bench patient [--config FILE] [--seeds N] [--seconds S] [--trace FILE ...] [--json]``

For each seed (and each ``--trace``) the deformable body of the config (default
``configs/sim_patient.toml``) breathes freely for ``--seconds`` (default 60) and is sampled at
20 Hz, with no controller in the loop. Per skin marker: the peak-to-peak amplitude along its
first principal direction (max minus min of the projection), grouped by region (thoracic above
``[simulation.body.skin] boundary_y_mm``, abdominal below); between markers, the largest angle
between their principal directions (the direction spread); over the breath, the rigid-fit
residual of the true markers (Horn's fit of the CT markers onto them: median and p95); the
target's peak-to-peak along its principal direction, and its phase lag behind the skin's mean
motion (cross-correlation peak). Printed beside the figures issue 40 quotes for recorded skin
markers on volunteers (3-17 mm peak to peak, directions up to ~50 deg apart, rigid-fit residual
0.6-3.4 mm median per person, p95 up to ~6 mm) and the tumour motion of AAPM TG-76 (Keall et
al. 2006: liver and lung 5-25 mm superior-inferior).

Runtime: the body's evaluation per stereo pair (skin, normals, entry, target), the simulated
camera's render per pair with the rigid and the deformable body (a manual clock, no
controller), and one whole ``hil run`` of the config: procedure time over wall time (how much
faster than real time the simulation runs).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.world import SimWorld
from hil.cli.cmd_run import run_procedure
from hil.clock import ManualClock
from hil.config import SetupConfig, build_devices, load_setup
from hil.config.body import BodyConfig
from hil.config.overrides import TRACE_FORMATS, with_trace
from hil.controller.plan_file import load_plan
from hil.errors import HilError
from hil.log import configure_logging

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CONFIG = ROOT / "configs" / "sim_patient.toml"
RECORDED = {"skin_ptp_mm": "3-17", "direction_spread_deg": "up to ~50",
            "rigid_residual_mm_median": "0.6-3.4", "rigid_residual_mm_p95": "up to ~6",
            "target_ptp_mm (liver/lung SI)": "5-25"}


def _principal(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = xyz - xyz.mean(axis=0)
    axis = np.linalg.svd(c, full_matrices=False)[2][0]
    axis = axis if axis[2] >= 0 else -axis
    return c @ axis, axis


def _lag_s(a: np.ndarray, b: np.ndarray, dt: float, max_s: float = 1.5) -> float:
    """How late ``b`` follows ``a`` (s), by the cross-correlation peak within +-max_s."""
    a = (a - a.mean()) / (a.std() or 1.0)
    b = (b - b.mean()) / (b.std() or 1.0)
    n = round(max_s / dt)
    lags = range(-n, n + 1)
    corr = [float(np.mean(a[max(0, -k):len(a) - max(0, k)] * b[max(0, k):len(b) - max(0, -k)]))
            for k in lags]
    return dt * list(lags)[int(np.argmax(corr))]


def body_statistics(setup: SetupConfig, seconds: float) -> dict[str, Any]:
    """The free-breathing body's statistics (module doc) for one setup."""
    clock = ManualClock()
    world = SimWorld(setup.simulation, setup.frames, clock)
    dt = 0.05
    times = np.arange(0.0, seconds, dt)
    T_image_from_optical = world.T_optical_from_image0.inverse()
    markers, target, residual = [], [], []
    for t in times:
        t_ns = clock.now_ns() + round(t * 1e9)
        b = world.body_state(t_ns)
        markers.append(T_image_from_optical.apply(b.markers_mm))
        target.append(T_image_from_optical.apply(b.target_mm[None, :])[0])
        residual.append(world.body_rigid_residual_mm(t_ns))
    m = np.array(markers)
    boundary = setup.simulation.body.skin.boundary_y_mm
    ptp: dict[str, list[float]] = {"thoracic": [], "abdominal": []}
    axes = []
    motion = np.zeros(len(times))
    for i in range(m.shape[1]):
        proj, axis = _principal(m[:, i])
        region = "thoracic" if world.phantom.markers_mm[i, 1] > boundary else "abdominal"
        ptp[region].append(float(proj.max() - proj.min()))
        axes.append(axis)
        motion += proj
    all_ptp = [x for v in ptp.values() for x in v]
    spread = max(math.degrees(math.acos(min(1.0, abs(float(a @ b))))) for a in axes for b in axes)
    tproj, _ = _principal(np.array(target))
    return {
        "skin_ptp_mm": {r: [round(x, 2) for x in v] for r, v in ptp.items()},
        "skin_ptp_mm_range": [round(min(all_ptp), 2), round(max(all_ptp), 2)],
        "direction_spread_deg": round(spread, 1),
        "rigid_residual_mm_median": round(float(np.median(residual)), 3),
        "rigid_residual_mm_p95": round(float(np.percentile(residual, 95)), 3),
        "target_ptp_mm": round(float(tproj.max() - tproj.min()), 2),
        "target_lag_s": round(_lag_s(motion, tproj if np.corrcoef(motion, tproj)[0, 1] >= 0 else -tproj, dt),
                              2),
    }


def _render_ms(setup: SetupConfig, frames: int) -> dict[str, float]:
    """Median ms per stereo pair: the body's evaluation and the simulated camera's grab."""
    clock = ManualClock()
    devices = build_devices(setup, clock)
    camera = devices.camera
    world: SimWorld = camera.world  # type: ignore[attr-defined]
    body_s, grab_s = [], []
    devices.open_all()
    try:
        for _ in range(frames):
            t0 = time.perf_counter()
            world.body_state(clock.now_ns())
            body_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            camera.grab(1.0)
            grab_s.append(time.perf_counter() - t0)
    finally:
        devices.close_all()
    return {"body_ms": round(1e3 * float(np.median(body_s)), 4),
            "render_ms": round(1e3 * float(np.median(grab_s)), 3)}


def _realtime_factor(cfg_path: Path, setup: SetupConfig) -> dict[str, float]:
    plan = load_plan(cfg_path.resolve().parent / "plans" / f"{cfg_path.stem}_plan.json")
    with tempfile.TemporaryDirectory(prefix="bench_patient_") as tmp:
        t0 = time.perf_counter()
        s = run_procedure(cfg_path, setup, plan, auto=True, session_dir=Path(tmp))
        wall = time.perf_counter() - t0
    return {"procedure_s": round(s.duration_s, 2), "wall_s": round(wall, 2),
            "faster_than_real_time": round(s.duration_s / wall, 2)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/bench patient", description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(DEFAULT_CONFIG),
                    help="setup TOML (default: configs/sim_patient.toml)")
    ap.add_argument("--seeds", type=int, default=12, help="seeds of the model (default 12)")
    ap.add_argument("--seconds", type=float, default=60.0, help="free breathing per seed (default 60 s)")
    ap.add_argument("--trace", action="append", default=[], metavar="FILE",
                    help="also drive the body by this trace (repeatable; docs/traces.md)")
    ap.add_argument("--trace-format", default="auto", choices=TRACE_FORMATS)
    ap.add_argument("--frames", type=int, default=60, help="stereo pairs timed per body (default 60)")
    ap.add_argument("--no-run", action="store_true", help="skip the whole hil run (real-time factor)")
    ap.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = ap.parse_args(argv)
    configure_logging(level="error")
    cfg_path = Path(args.config)
    try:
        base = load_setup(cfg_path)
        if base.simulation.body.model != "deformable":
            base = base.model_copy(update={"simulation": base.simulation.model_copy(
                update={"body": base.simulation.body.model_copy(update={"model": "deformable"})})})
        per_seed = []
        for seed in range(1, args.seeds + 1):
            setup = base.model_copy(update={"simulation": base.simulation.model_copy(update={"seed": seed})})
            per_seed.append({"seed": seed, **body_statistics(setup, args.seconds)})
        per_trace = {}
        for path in args.trace:
            per_trace[path] = body_statistics(with_trace(base, path, args.trace_format), args.seconds)
        rigid_sim = base.simulation.model_copy(update={"body": BodyConfig()})
        rigid = base.model_copy(update={"simulation": rigid_sim})
        cost = {"rigid": _render_ms(rigid, args.frames), "deformable": _render_ms(base, args.frames)}
        run = None if args.no_run else _realtime_factor(cfg_path, base)
    except HilError as exc:
        print(f"tools/bench patient: error: {exc}", file=sys.stderr)
        return 2
    out = {"config": str(cfg_path), "seconds": args.seconds, "recorded": RECORDED, "per_seed": per_seed,
           "per_trace": per_trace, "cost_per_pair": cost, "hil_run": run, "summary": _summary(per_seed)}
    if args.json:
        print(json.dumps(out))
    else:
        _print(out)
    return 0


def _summary(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    def rng(key: str) -> list[float]:
        vals = [float(r[key]) for r in per_seed]
        return [round(min(vals), 2), round(max(vals), 2)]
    thor = [x for r in per_seed for x in r["skin_ptp_mm"]["thoracic"]]
    abd = [x for r in per_seed for x in r["skin_ptp_mm"]["abdominal"]]
    return {"skin_ptp_mm_thoracic": [min(thor, default=0.0), max(thor, default=0.0)],
            "skin_ptp_mm_abdominal": [min(abd, default=0.0), max(abd, default=0.0)],
            "direction_spread_deg": rng("direction_spread_deg"),
            "rigid_residual_mm_median": rng("rigid_residual_mm_median"),
            "rigid_residual_mm_p95": rng("rigid_residual_mm_p95"),
            "target_ptp_mm": rng("target_ptp_mm"), "target_lag_s": rng("target_lag_s")}


def _print(out: dict[str, Any]) -> None:
    s = out["summary"]
    print(f"deformable body of {out['config']}, {len(out['per_seed'])} seeds x {out['seconds']:g} s "
          "free breathing")
    print(f"{'':34}{'simulated (range over seeds)':>32}{'recorded (issue 40, TG-76)':>30}")
    def span(key: str, unit: str, digits: int = 1) -> str:
        lo, hi = s[key]
        return f"{lo:.{digits}f}-{hi:.{digits}f} {unit}"
    rows = [("skin peak-to-peak, thoracic", span("skin_ptp_mm_thoracic", "mm"), "3-17 mm"),
            ("skin peak-to-peak, abdominal", span("skin_ptp_mm_abdominal", "mm"), "3-17 mm"),
            ("direction spread", span("direction_spread_deg", "deg", 0), "up to ~50 deg"),
            ("rigid-fit residual, median", span("rigid_residual_mm_median", "mm", 2), "0.6-3.4 mm"),
            ("rigid-fit residual, p95", span("rigid_residual_mm_p95", "mm", 2), "up to ~6 mm"),
            ("target peak-to-peak", span("target_ptp_mm", "mm"), "5-25 mm"),
            ("target lag behind the skin", span("target_lag_s", "s", 2), "-0.65..+0.50 s (Hoisak 2004)")]
    for label, ours, rec in rows:
        print(f"{label:34}{ours:>32}{rec:>30}")
    for path, st in out["per_trace"].items():
        print(f"trace {path}: skin {st['skin_ptp_mm_range'][0]}-{st['skin_ptp_mm_range'][1]} mm, spread "
              f"{st['direction_spread_deg']} deg, residual median/p95 {st['rigid_residual_mm_median']}/"
              f"{st['rigid_residual_mm_p95']} mm, target {st['target_ptp_mm']} mm")
    c = out["cost_per_pair"]
    print(f"cost per stereo pair (median): body {c['deformable']['body_ms']} ms (rigid "
          f"{c['rigid']['body_ms']} ms); camera render {c['deformable']['render_ms']} ms (rigid "
          f"{c['rigid']['render_ms']} ms)")
    if out["hil_run"]:
        r = out["hil_run"]
        print(f"hil run: {r['procedure_s']} s of procedure in {r['wall_s']} s wall: "
              f"{r['faster_than_real_time']}x faster than real time")


if __name__ == "__main__":
    sys.exit(main())
