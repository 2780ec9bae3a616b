"""``hil run``: run a whole procedure (register -> plan -> approach -> gate -> compensate -> lock).

``hil run`` with no arguments runs ``configs/sim.toml`` with its bundled plan, auto-confirming,
faster than real time (simulated clock), and prints a summary (``--json``: one JSON object,
fields documented in docs/run.md). Exit code 0 when the procedure reached DONE, 1 otherwise.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import select
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from hil.clock import Clock, ManualClock, MonotonicClock
from hil.config import build_devices, default_setup_path, load_setup
from hil.config.overrides import TRACE_FORMATS, with_trace
from hil.config.setup import SetupConfig
from hil.controller.assembly import (
    RobotWrapper,
    build_controller,
    runtime_plugins,
    session_header,
    start_igtl,
    stereo_calibration,
    with_perception_process,
    with_servo_process,
    wrap_robot,
)
from hil.controller.controller import Controller
from hil.controller.fsm import Event, State
from hil.controller.metrics import RunSummary
from hil.controller.operator_input import AutoOperator, Operator, OperatorView
from hil.controller.perception import StereoMarkerLocator
from hil.controller.plan_file import ProcedurePlan, load_plan
from hil.errors import HilError, InputFileError
from hil.perception.process import PerceptionProcess
from hil.session.log import SessionLog

if TYPE_CHECKING:
    from hil.replay.live import LiveViewerPlugin

#: The live viewer's name in the run's plugin manager (hil.replay.live.PLUGIN_NAME).
LIVE_PLUGIN_NAME = "rerun_viewer"


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "run", help="run a whole procedure (default: the simulator, auto-confirmed)",
        description="Run register -> plan -> approach -> hold-breath gate -> compensate -> lock on the "
                    "devices of a setup. Without CONFIG: configs/sim.toml and its plan, --auto.")
    p.add_argument("config", nargs="?", help="setup TOML (default: the embedded configs/sim.toml)")
    p.add_argument("--plan", help="plan JSON (default: plans/<config name>_plan.json next to the config)")
    p.add_argument("--auto", action="store_true", help="confirm every confirmation automatically")
    p.add_argument("--seed", type=int, help="override [simulation] seed")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--session-dir", default="sessions",
                   help="where the session log goes (default: sessions/)")
    p.add_argument("--max-duration", type=float, help="stop after this many seconds of procedure time")
    p.add_argument("--no-report", action="store_true",
                   help="do not build the HTML report (hil report) after the session")
    p.add_argument("--trace", metavar="FILE",
                   help="drive the simulated patient by a recorded trace (docs/traces.md): the body becomes "
                        "deformable ([simulation.body.trace] path)")
    p.add_argument("--trace-format", default="auto", choices=TRACE_FORMATS,
                   help="the trace's format (default: told from the file)")
    p.add_argument("--viewer", metavar="FILE.rrd|ADDRESS", default=None,
                   help="stream the run live to Rerun: a .rrd file, or a viewer address such as "
                        "rerun+http://127.0.0.1:9876/proxy (docs/replay.md)")
    p.set_defaults(func=run)


class InteractiveOperator:
    """Asks on stderr and reads single-letter answers from stdin when a decision is needed.

    The question is asked once per decision; the answer is polled without blocking (``select``)
    when stdin is a real file, so the control loop keeps ticking (watchdogs, drift watch while
    locked) while the operator thinks. A stream without a file descriptor is read blocking.
    """

    def __init__(self, inp: TextIO = sys.stdin, out: TextIO = sys.stderr) -> None:
        self.inp, self.out = inp, out
        self._started = False
        self._quit = False
        self._asked: tuple[str, str | None] | None = None

    def _answer(self, key: tuple[str, str | None], prompt: str) -> str | None:
        if self._asked != key:
            self._asked = key
            self.out.write(prompt)
            self.out.flush()
        try:
            fd = self.inp.fileno()
        except (OSError, ValueError, AttributeError):
            fd = None
        if fd is not None:
            ready, _, _ = select.select([self.inp], [], [], 0.0)
            if not ready:
                return None
        line = self.inp.readline()
        self._asked = None
        if not line:
            self._quit = True
            return ""
        return line.strip().lower()[:1]

    def poll(self, view: OperatorView) -> Event | None:
        if not self._started and view.state is State.IDLE:
            self._started = True
            return Event.START_REQUESTED
        key = (view.state.value, view.pending)
        if view.pending is not None:
            a = self._answer(key, f"[{view.t_s:7.2f} s] {view.state.value}: confirm {view.pending}? "
                                  "[y]es / [a]bort: ")
            return Event.CONFIRM_REQUESTED if a == "y" else Event.ABORT_REQUESTED if a == "a" else None
        if view.state in (State.PAUSED, State.FAULT, State.SAFE_STOP):
            a = self._answer(key, f"[{view.t_s:7.2f} s] {view.state.value} ({view.last_reason}): [r]esume / "
                                  "re-[s]tart registration / re[t]ract / [q]uit: ")
            if a == "q":
                self._quit = True
            return {"r": Event.RESUME_REQUESTED, "s": Event.START_REQUESTED,
                    "t": Event.RETRACT_REQUESTED}.get(a or "")
        return None

    def finished(self, view: OperatorView) -> bool:
        return self._quit or view.state is State.DONE or (view.state is State.IDLE and view.started)


def _resolve(args: argparse.Namespace) -> tuple[Path, SetupConfig, ProcedurePlan, bool]:
    config_path = Path(args.config) if args.config else default_setup_path()
    setup = load_setup(config_path)
    auto = bool(args.auto or args.config is None)
    if args.seed is not None:
        if args.seed < 0:
            raise InputFileError("--seed", f"must be >= 0, got {args.seed}")
        sim = setup.simulation.model_copy(update={"seed": args.seed})
        setup = setup.model_copy(update={"simulation": sim})
    if args.trace:
        setup = with_trace(setup, args.trace, args.trace_format)
    if args.plan:
        plan_path = Path(args.plan)
    else:
        plan_path = config_path.resolve().parent / "plans" / f"{config_path.stem}_plan.json"
        if not plan_path.is_file():
            raise InputFileError(str(plan_path), "no bundled plan for this setup; give one with --plan")
    return config_path, setup, load_plan(plan_path), auto


def run_procedure(config_path: Path, setup: SetupConfig, plan: ProcedurePlan, *, auto: bool,
                  session_dir: Path, max_duration_s: float | None = None,
                  clock: Clock | None = None, operator: Operator | None = None,
                  robot_wrapper: RobotWrapper | None = None, viewer: str | None = None,
                  err: TextIO | None = None) -> RunSummary:
    """Build the devices of ``setup``, run the procedure, close everything; return the summary.

    Simulated setups run on a :class:`ManualClock` (faster than real time) unless
    ``[simulation] real_time``; other setups on the monotonic clock. ``operator`` overrides the
    auto / interactive operator chosen by ``auto``. ``robot_wrapper`` (see :data:`RobotWrapper`)
    puts a wrapper between the controller and the robot driver. ``viewer`` (a ``.rrd`` path or
    a Rerun viewer address) streams the run live (:mod:`hil.replay.live`); its counts and hook
    cost go to ``err`` (default: the current ``sys.stderr``) as one line when it closes.
    """
    err = sys.stderr if err is None else err
    if clock is None:
        from plugins.manager import default_registry

        reg = default_registry()
        simulated = any(reg.get(role, str(getattr(cfg, "driver", ""))).simulated
                        for role, cfg in setup.device_sections().items())
        fast = simulated and not setup.simulation.real_time
        clock = ManualClock(1_000_000_000) if fast else MonotonicClock()
    devices = build_devices(setup, clock)
    stereo_calibration(setup, devices.camera)  # none anywhere: refused before any device opens
    if robot_wrapper is not None:
        devices = wrap_robot(devices, robot_wrapper)
    else:
        devices = with_servo_process(setup, devices, clock)  # [servo] process: on the wall clock
        devices = with_perception_process(setup, devices, clock)  # [perception] process: likewise
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%S%fZ")
    header = {**session_header(config_path, setup, plan, devices, clock), "auto": auto}
    igtl = start_igtl(setup, clock)  # first: a busy port is a usage error, nothing else started
    live: LiveViewerPlugin | None = None
    try:
        live = None if viewer is None else open_viewer_stream(viewer)
        session = SessionLog(session_dir / f"session_{stamp}.jsonl", clock, header)
        devices.open_all()
    except BaseException:
        if igtl is not None:
            igtl.close()
        close_viewer_stream(live, viewer, err)
        raise
    ctl: Controller | None = None
    try:
        try:
            hooks = runtime_plugins(igtl, plan)
            if live is not None:
                hooks.register(live, LIVE_PLUGIN_NAME)
            ctl = build_controller(
                setup, plan, devices, clock=clock, session=session,
                operator=operator or (AutoOperator() if auto else InteractiveOperator()),
                hooks=hooks,
            )
            if live is not None:   # the simulator's true positions too (one attribute read a tick)
                meter = ctl.truth_meter
                live.follow_truth(lambda: meter.last_positions)
            summary = ctl.run(max_duration_s)
            if isinstance(feed := devices.camera.perception_feed, PerceptionProcess):   # located there
                summary.locate_ms = feed.locate_figures()
            elif isinstance(ctl.locate, StereoMarkerLocator):
                summary.locate_ms = ctl.locate.locate_ms()
        finally:
            devices.close_all()
            if igtl is not None:
                igtl.close()
            close_viewer_stream(live, viewer, err)
    except BaseException as exc:
        # Ctrl-C, SIGTERM, an error building the controller: the devices are closed (the arm
        # stopped); the log still ends with session_closed, saying how and in which state
        session.close(final_state="interrupted" if isinstance(exc, KeyboardInterrupt) else "error",
                      state=None if ctl is None else ctl.state, ended_by=type(exc).__name__)
        raise
    session.close(final_state=summary.final_state, states=summary.states)
    summary.session_log_sha256 = session.head_sha256  # the chain head, published outside the file
    return summary


def open_viewer_stream(target: str) -> LiveViewerPlugin:
    """The live Rerun stream of ``--viewer`` (:func:`hil.replay.live.open_live_viewer`)."""
    from hil.replay.live import open_live_viewer

    return open_live_viewer(target)


def close_viewer_stream(live: LiveViewerPlugin | None, target: str | None, err: TextIO) -> None:
    """Close the live stream (on every path) and say on ``err`` what it did."""
    if live is None:
        return
    from hil.replay.live import stream_line

    live.close()
    err.write(f"hil run: {stream_line(live, str(target))}\n")


def build_session_report(session_log: str, err: TextIO) -> str | None:
    """Build the HTML report of a finished session (``hil report``, default output directory)
    and return its path; None (with one line on ``err``) when it cannot be built -- the
    procedure's result stands without it."""
    try:
        from hil.report import build_report
    except ImportError as exc:
        err.write(f"hil run: report not built: it needs matplotlib (the [report] extra): {exc}\n")
        return None
    try:
        return str(build_report(session_log).html_path)
    except HilError as exc:
        err.write(f"hil run: report not built: {exc}\n")
        return None


def _fmt(x: float | None, unit: str, digits: int = 3) -> str:
    return "n/a" if x is None else f"{x:.{digits}f} {unit}"


def print_text(s: RunSummary, out: TextIO) -> None:
    out.write(f"final state      {s.final_state}\n")
    out.write("timeline\n")
    for row in s.timeline:
        reason = f"  ({row['reason']})" if row.get("reason") else ""
        out.write(f"  {row['t_s']:8.3f} s  {row['state']:<11}{reason}\n")
    out.write(f"FRE              {_fmt(s.fre_mm, 'mm')}\n")
    out.write(f"expected TRE     {_fmt(s.tre_expected_mm, 'mm')}\n")
    out.write(f"robot reg. FRE   {_fmt(s.robot_fre_mm, 'mm')}\n")
    out.write(f"lock error       {_fmt(s.lock_error_mm, 'mm')}, direction "
              f"{_fmt(s.lock_direction_error_deg, 'deg')} (vs simulator truth)\n")
    if s.target_error_mm is not None:
        out.write(f"target error     {_fmt(s.target_error_mm, 'mm')} at lock, max "
                  f"{_fmt(s.target_error_max_mm, 'mm')} over the hold (guide axis to the true target)\n")
    if s.body_rigid_residual_mm_p95:
        out.write(f"body non-rigid   p95 {_fmt(s.body_rigid_residual_mm_p95, 'mm')} "
                  "(rigid-fit residual of the true skin markers)\n")
    out.write(f"compensation     RMS {_fmt(s.comp_error_rms_mm, 'mm')}, "
              f"p95 {_fmt(s.comp_error_p95_mm, 'mm')}\n")
    out.write(f"latency          p50 {_fmt(s.latency_ms['p50'], 'ms', 1)}, "
              f"p95 {_fmt(s.latency_ms['p95'], 'ms', 1)}"
              " (exposure -> command)\n")
    out.write(f"locate           p50 {_fmt(s.locate_ms['p50'], 'ms', 1)}, "
              f"p95 {_fmt(s.locate_ms['p95'], 'ms', 1)} (markers per stereo pair)\n")
    out.write(f"time to lock     {_fmt(s.time_to_lock_s, 's', 2)}\n")
    if s.faults:
        out.write(f"faults           {'; '.join(s.faults)}\n")
    out.write(f"session log      {s.session_log}\n")
    if s.session_log_sha256 is not None:
        out.write(f"chain head       {s.session_log_sha256} (SHA-256 of its last line; also in .head)\n")
    if s.report is not None:
        out.write(f"report           {s.report}\n")


def run(args: argparse.Namespace) -> int:
    config_path, setup, plan, auto = _resolve(args)
    summary = run_procedure(config_path, setup, plan, auto=auto, session_dir=Path(args.session_dir),
                            max_duration_s=args.max_duration, viewer=args.viewer)
    if not args.no_report:
        summary.report = build_session_report(summary.session_log, sys.stderr)
    if args.json:
        sys.stdout.write(json.dumps(summary.to_dict(), default=str) + "\n")
    else:
        print_text(summary, sys.stdout)
    return 0 if summary.final_state == State.DONE.value else 1

