"""``hil soak --minutes M [--rate 125|500] [--no-rt] [--perception-process] [--json]``:
real-time soak of the simulated procedure in compensation, with the servo loop in its own process
at the robot's rate (``--perception-process``: the camera grabbed, rendered and located in the
perception process, else in the supervisor); reports what the OS granted the servo process
(SCHED_FIFO, CPU, locked memory), servo period jitter (p50/p99/max), late periods beside their
documented bound and the host's steal of the loop's CPU (on a VM), frame-to-command latency,
operator stop -> stop command, and memory growth of every process (definitions in
hil/soak/soak.py and docs/benchmarks.md). ``--no-rt`` runs the same soak without asking for
real-time scheduling (the comparison). ``--faults-every S`` injects a transient fault
(camera frame drop, robot disconnect, protective stop, occlusion, motion lag, in turn) every S
seconds: the soak resumes after each (registering again when the gate stays shut) and reports
what the controller said and how long it took to compensate again. Stdout: the figures
(``--json``: one object, with ``passed``). ``--camera-clock-ppm`` sets the simulated camera's clock
rate error (default: the setup's, else 50 ppm, so pairs sweep the servo periods' phase as a
free-running camera's do; JSON ``camera_clock_ppm``). Exit code 0 when the run compensated without refused
steps and without a fault that the injected ones do not explain, and came back from every
injected fault it detected; 1 otherwise (late periods over their bound are printed, not a
failure: the host's steal can cause them). ``--probe-host S`` (default 10) runs S seconds of fixed
work with the servo's real-time set-up before and after the soak (hil/soak/probe.py) and prints
its late periods beside the soak's (JSON ``host_probe``): what the machine alone does.
``--viewer FILE.rrd|ADDRESS`` streams the soak live through the viewer plugin (docs/replay.md) and
reports what it adds to a supervisor tick (JSON ``viewer``: counts and ``hook_ms`` p50/p99/max);
compare the servo figures with a soak without it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from hil.soak.host import STEAL_WINDOW_S

if TYPE_CHECKING:
    from hil.soak.soak import SoakResult


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "soak",
        help="real-time soak of the simulated procedure in compensation (jitter, deadlines, memory)",
        description="Run the simulated procedure on the wall clock, keep it compensating for M minutes "
        "with the servo loop in its own (real-time) process at the robot's rate, and report what the OS "
        "granted, servo period jitter, late periods, frame-to-command latency and memory growth.",
    )
    p.add_argument("--no-rt", action="store_true",
                   help="do not ask for real-time scheduling for the servo process (the comparison run)")
    p.add_argument("--perception-process", action="store_true",
                   help="grab, render and locate in the perception process, as [perception] process = "
                        "\"auto\" does on the wall clock (the issue's set-up); without it, in the "
                        "supervisor (the comparison)")
    p.add_argument("--minutes", type=float, default=1.0, help="minutes of compensation (default 1)")
    p.add_argument(
        "--rate",
        type=float,
        default=125.0,
        help="robot servo rate, Hz: 125 (UR3 CB3, default) or 500 (e-Series)",
    )
    p.add_argument("--faults-every", type=float, default=0.0, metavar="S",
                   help="inject a transient fault every S seconds (>= 10; default 0: none), cycling "
                        "through camera frame drop, robot disconnect, protective stop, occlusion, motion "
                        "lag; the soak resumes after each and reports it")
    p.add_argument("--probe-host", type=float, default=10.0, metavar="S",
                   help="before and after the soak, run S seconds of fixed work at the servo rate with the "
                        "servo's real-time set-up and none of our code (tools/bench host), so the soak's "
                        "late periods can be read against what the machine alone does (default 10; 0: no "
                        "probe)")
    p.add_argument("--camera-clock-ppm", type=float, default=None, metavar="PPM",
                   help="run the simulated camera's frame clock PPM fast against the host's, as a real "
                        "camera's crystal is (default: the setup's [simulation.rig_errors] "
                        "camera_clock_rate_error_ppm, else 50; 0: on the host's clock, so every pair keeps "
                        "one phase of the servo periods for the whole soak)")
    p.add_argument("--viewer", metavar="FILE.rrd|ADDRESS", default=None,
                   help="stream the soak live to a Rerun recording file or viewer address (the live "
                        "viewer plugin, docs/replay.md) and report its cost per supervisor tick")
    p.add_argument("--config", help="simulated setup TOML (default: the embedded configs/sim.toml)")
    p.add_argument("--plan", help="plan JSON (default: plans/<config name>_plan.json next to the config)")
    p.add_argument("--session-dir", default="sessions", help="where the session log goes (default sessions/)")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    p.set_defaults(func=run)


def _latency_bound(res: SoakResult) -> str:
    """Frame -> command beside the bound the camera's own latency, the locate time and the servo
    period imply (hil.soak.soak.latency_bound)."""
    from hil.soak.soak import LATENCY_HANDOVER_MS, LATENCY_P99_MARGIN_MS  # imported lazily, as the soak
    cam, bound = res.camera_latency_ms, res.latency_bound_ms
    if not bound:
        return "n/a (the camera's latency is measured in the perception process: --perception-process)"
    f2c = res.frame_to_command_ms
    verdicts = []
    for k in ("p50", "p99"):
        got, lim = f2c.get(k), bound.get(k)
        verdicts.append("n/a" if got is None or lim is None else ("within" if got <= lim else "OVER"))
    return (f"p50 {bound['p50']:.2f} ms (camera p50 {cam['p50']:.2f} + locate p50 "
            f"{res.locate_ms['p50']:.2f} + period {1e3 / res.rate_hz:g} + {LATENCY_HANDOVER_MS:g}): "
            f"{verdicts[0]}; "
            f"p99 {bound['p99']:.2f} ms (+ {LATENCY_P99_MARGIN_MS:g}): {verdicts[1]}; "
            f"camera p99 {cam['p99']:.2f} ms")


def _fmt(d: dict[str, float | None]) -> str:
    return " / ".join("n/a" if d.get(k) is None else f"{d[k]:.3f}" for k in ("p50", "p99", "max"))


def _steal(steal: dict[str, float | None], cpu: int | None) -> str:
    """The host steal line: the loop's CPU and the mean of all, or why there is no figure."""
    if not steal:
        return "n/a (/proc/stat not readable)"
    parts = []
    if steal.get("loop_cpu") is not None:
        parts.append(f"{steal['loop_cpu']} % on the loop's CPU {cpu}")
    if steal.get("all_cpus") is not None:
        parts.append(f"{steal['all_cpus']} % mean of all CPUs")
    return ", ".join(parts) + " (the hypervisor's; late periods include what it took)"


def _late_bound(res: Any) -> str:
    """The late-bound line: the late share over the host's steal-free windows beside the
    documented bound, or why there is none."""
    bound = res.late_fraction_bound()
    granted = "real time granted" if res.rt_granted.get("realtime") else "no real time"
    free = res.steal_free
    if not free:
        return f"n/a (/proc/stat not readable; documented bound {100 * bound:g} %, {granted})"
    if not free["intervals"]:
        return (f"n/a: the host took the loop's CPU in every {1e3 * STEAL_WINDOW_S:g} ms window "
                f"(documented bound {100 * bound:g} %, {granted})")
    met = "within" if free["late_fraction"] <= bound else "OVER"
    return (f"{free['late']} late of {free['intervals']} intervals ({100 * free['late_fraction']:.2f} %) "
            f"in the {free['clean_windows']} of {free['windows']} windows without steal: {met} the "
            f"documented {100 * bound:g} % ({granted})")


#: the probe's figures the soak keeps (hil/soak/probe.py)
PROBE_KEYS = ("seconds", "intervals", "late", "longest_interval_ms", "work_wall_ms", "stretched_over_2x",
              "host_steal_percent", "rt_summary")


def _probe(seconds: float, rate_hz: float, when: str) -> dict[str, Any]:
    """The host probe's figures (:data:`PROBE_KEYS` and ``late_per_10k``), or ``{"error": why}``."""
    from hil.soak.probe import per_10k, probe_in_subprocess

    print(f"hil soak: probing the host for {seconds:g} s {when} the soak (fixed work, none of our code)",
          file=sys.stderr, flush=True)
    try:
        out = probe_in_subprocess(seconds, rate_hz)
    except RuntimeError as exc:
        print(f"hil soak: {exc}", file=sys.stderr, flush=True)
        return {"error": str(exc)}
    return {**{k: out[k] for k in PROBE_KEYS}, "late_per_10k": round(per_10k(out), 1)}


def _probe_text(p: dict[str, Any]) -> str:
    if "error" in p:
        return f"n/a ({p['error']})"
    return (f"{p['late']} late of {p['intervals']} ({p['late_per_10k']:g} in 10,000), longest "
            f"{p['longest_interval_ms']} ms, steal {p['host_steal_percent'].get('loop_cpu')} %")


def run(args: argparse.Namespace) -> int:
    from hil.config import default_setup_path
    from hil.soak.soak import run_soak

    if not args.probe_host >= 0:
        print(f"hil soak: --probe-host must be >= 0 s, got {args.probe_host}", file=sys.stderr)
        return 2
    config = Path(args.config) if args.config else default_setup_path()
    probe: dict[str, Any] = {}
    if args.probe_host > 0:
        probe["before"] = _probe(args.probe_host, float(args.rate), "before")
    res = run_soak(
        args.minutes,
        float(args.rate),
        config=config,
        plan=args.plan,
        session_dir=Path(args.session_dir),
        realtime=not args.no_rt,
        perception_process=args.perception_process,
        camera_clock_ppm=args.camera_clock_ppm,
        faults_every_s=args.faults_every,
        viewer=args.viewer,
        progress=lambda m: print(f"hil soak: {m}", file=sys.stderr, flush=True),
    )
    if args.probe_host > 0:
        probe["after"] = _probe(args.probe_host, float(args.rate), "after")
    if args.json:
        sys.stdout.write(json.dumps({**res.to_dict(), "host_probe": probe, "passed": res.passed()}) + "\n")
    else:
        _print_text(res, probe)
    return 0 if res.passed() else 1


def _print_memory(out: TextIO, res: SoakResult) -> None:
    """The memory lines of the text output: heap trims, cycle collections, each process's RSS."""
    ht = res.heap_trim
    out.write(f"heap trims           {ht.get('trims', 0)} ({ht.get('released', 0)} gave memory back; "
              f"longest {ht.get('max_ms')} ms; [procedure] heap_trim_every_s)\n")
    out.write(f"cycle collections    {ht.get('collections', 0)} ({ht.get('collected', 0)} objects freed; "
              f"longest {ht.get('collect_max_ms')} ms; {ht.get('frozen_objects', 0)} start-up objects "
              "frozen)\n")
    mems = [("memory supervisor", res.rss_mb), ("memory servo proc.", res.servo_rss_mb)]
    if res.perception_rss_mb:
        mems.append(("memory perception", res.perception_rss_mb))
    for label, r in mems:
        out.write(
            f"{label:<21}{r.get('after_warmup')} -> {r.get('end')} MB, "
            f"growth {r.get('growth')} MB, slope {r.get('slope_mb_per_min')} MB/min\n"
        )
    if res.file_rss_growth:
        grown = ", ".join(f"{Path(str(row['file'])).name} +{row['kb']} kB (minute {row['first_grew_min']})"
                          for row in res.file_rss_growth[:4])
        out.write(f"file pages grown     {grown}\n")


def _print_text(res: SoakResult, probe: dict[str, Any]) -> None:
    """The soak's figures as text lines on stdout (the module doc lists them)."""
    out = sys.stdout
    from hil.servo.rt import RtGranted

    out.write(f"servo rate           {res.rate_hz:g} Hz (period {1e3 / res.rate_hz:.3f} ms)\n")
    out.write(f"servo process        {RtGranted.from_dict(res.rt_granted).summary()}\n")
    cpus = "every CPU" if res.supervisor_cpus is None else "CPU " + ", ".join(map(str, res.supervisor_cpus))
    out.write(f"supervisor on        {cpus} (with the perception process it started)\n")
    out.write(f"servo process CPU    {res.servo_cpu_percent} % of one CPU in compensation\n")
    out.write(
        f"compensation         {res.compensate_s:.1f} s, {res.servo_commands} servo commands, "
        f"{res.resumes} resume(s), {res.reregistrations} re-registration(s)\n"
    )
    out.write(f"period p50/p99/max   {_fmt(res.period_ms)} ms\n")
    out.write(f"jitter p50/p99/max   {_fmt(res.jitter_ms)} ms\n")
    out.write(
        f"missed deadlines     {res.missed_deadlines} of {res.intervals} intervals "
        f"({100 * res.missed_fraction:.2f} %), longest gap {res.longest_gap_ms} ms\n"
    )
    out.write(f"late bound           {_late_bound(res)}\n")
    for when, p in probe.items():
        out.write(f"machine alone {when:<7}{_probe_text(p)} (fixed work, tools/bench host)\n")
    lc = res.late_causes
    out.write(f"late causes          woke late {lc['woke_late']} (the OS or host did not run the loop), "
              f"work overran {lc['overran']} ({lc['overran_off_cpu']} with the loop off its CPU for "
              f"over a period); longest wake-up delay {lc['longest_wake_delay_ms']} ms, step "
              f"{lc['longest_step_ms']} ms ({lc['longest_step_cpu_ms']} ms on its CPU, "
              f"{lc['longest_off_cpu_ms']} ms off)\n")
    out.write(f"host steal           {_steal(res.host_steal_percent, res.rt_granted.get('cpu'))}\n")
    out.write(f"frames               {res.compensation_frames} in compensation, "
              f"{res.frames_overwritten} overwritten; {res.stale_periods} period(s) on a stale "
              f"setpoint, {res.setpoint_busy_periods} on the last one (a write in progress)\n")
    out.write(f"frame->command       {_fmt(res.frame_to_command_ms)} ms (p50/p99/max)\n")
    out.write(f"frame->setpoint      {_fmt(res.frame_to_setpoint_ms)} ms (p50/p99/max; the supervisor's "
              f"part, before the loop's next period)\n")
    sp = res.setpoint_us
    out.write(f"setpoint work        {sp.get('p50_us')} / {sp.get('p99_us')} / {sp.get('max_us')} us "
              f"(p50/p99/max over {sp.get('count', 0)} pairs; predictor {res.predictor}: its update "
              f"and the setpoint, inside frame->setpoint)\n")
    cf = res.change_fit_us
    out.write(f"change estimate      {cf.get('p50_us')} / {cf.get('p99_us')} / {cf.get('max_us')} us "
              f"(p50/p99/max over {cf.get('count', 0)} pairs; estimator {res.estimator})\n")
    pm = res.pair_model_us
    out.write(f"models per pair      {pm.get('p50_us')} / {pm.get('p99_us')} / {pm.get('max_us')} us "
              f"(p50/p99/max over {pm.get('count', 0)} pairs: each pair's change estimate and "
              f"setpoint work added)\n")
    out.write(f"latency bound        {_latency_bound(res)}\n")
    out.write(f"camera clock         {res.camera_clock_ppm:g} ppm off the host's (--camera-clock-ppm)\n")
    out.write(f"stop->command        {_fmt(res.stop_to_command_ms)} ms (p50/p99/max)\n")
    where = "perception process" if res.perception_rss_mb else "supervisor"
    loc = " / ".join("n/a" if res.locate_ms.get(k) is None else f"{res.locate_ms[k]:.2f}"
                     for k in ("p50", "p95"))
    out.write(f"locate               {loc} ms (p50/p95, {where})\n")
    _print_memory(out, res)
    out.write(f"refused steps        {res.limit_violations} (the loop's limit check; none reached "
              "the driver)\n")
    out.write(f"following error      peak {res.following_peak_mm:.3f} mm, "
              f"{res.following_faults} fault(s)\n")
    if res.viewer:
        v = res.viewer
        out.write(f"live viewer          hook {_fmt(v['hook_ms'])} ms per call (p50/p99/max, "
                  f"{v['hook_calls']} calls); {v['written']} of {v['offered']} snapshots written, "
                  f"{v['dropped']} dropped\n")
    for f in res.transient_faults:
        back = f["back_in_compensation_s"]
        again = "" if back is None else f"; compensating again after {back:.1f} s"
        out.write(f"injected {f['kind']:<16} at {f['onset_s']:>7.1f} s for {f['duration_s']:g} s: "
                  f"{f['detected']}{again}\n")
    out.write(f"final state          {res.final_state}; faults: {'; '.join(res.faults) or 'none'}\n")
    out.write(f"unexplained faults   {'; '.join(res.unexplained_faults) or 'none'}\n")
    out.write(f"verdict              {'passed' if res.passed() else 'FAILED'}\n")
    out.write(f"session log          {res.session_log}\n")
