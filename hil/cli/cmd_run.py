"""``hil run``: run a whole procedure (register -> plan -> approach -> gate -> compensate -> lock).

``hil run`` with no arguments runs ``configs/sim.toml`` with its bundled plan, auto-confirming,
faster than real time (simulated clock), and prints a summary (``--json``: one JSON object,
fields documented in docs/run.md). Exit code 0 when the procedure reached DONE, 1 otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import hashlib
import json
import select
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from drivers.interfaces.robot import Robot
from hil.clock import Clock, ManualClock, MonotonicClock
from hil.config import Devices, build_devices, default_setup_path, load_setup
from hil.config.setup import SetupConfig
from hil.controller.controller import Controller
from hil.controller.fsm import Event, State
from hil.controller.metrics import RunSummary
from hil.controller.observers import HookCaller, TickObserver
from hil.controller.operator_input import AutoOperator, Operator, OperatorView
from hil.controller.perception import CollinearNeedleChecker, StereoMarkerLocator, StereoNeedleChecker
from hil.controller.perception import StereoMarkerLocator as _Locator
from hil.controller.plan_file import ProcedurePlan, load_plan
from hil.controller.planning import RigGeometry
from hil.controller.tracker_use import TrackerUse
from hil.controller.truth import BreathHoldCoach, GroundTruth
from hil.errors import HilError, InputFileError
from hil.geometry.transform import RigidTransform
from hil.rigcal.apply import flange_markers_mm, rig_calibration_sha256, with_rig_time_offsets
from hil.session.log import SessionLog, file_sha256
from hil.tracking.session import load_tracker_calibration
from hil.vision.camera_model import StereoCalibration, load_calibration
from hil.vision.tracking import TrackingParams
from plugins.manager import HilPlugins

if TYPE_CHECKING:
    from hil.igtl.server import IgtlServer


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
    if args.plan:
        plan_path = Path(args.plan)
    else:
        plan_path = config_path.resolve().parent / "plans" / f"{config_path.stem}_plan.json"
        if not plan_path.is_file():
            raise InputFileError(str(plan_path), "no bundled plan for this setup; give one with --plan")
    return config_path, setup, load_plan(plan_path), auto


def _rig(setup: SetupConfig) -> RigGeometry:
    tcp_cfg = getattr(setup.robot, "T_flange_from_tcp", None)
    T_flange_from_tcp = tcp_cfg.as_transform() if tcp_cfg is not None else RigidTransform.identity()
    return RigGeometry(setup.frames.T_flange_from_guide.as_transform(),
                       flange_markers_mm(setup), T_flange_from_tcp)  # [calibration] rig, else CAD


def _calibration(setup: SetupConfig, camera: object) -> StereoCalibration:
    if setup.calibration.stereo is not None:
        return load_calibration(setup.calibration.stereo)
    cal = getattr(camera, "calibration", None)
    if isinstance(cal, StereoCalibration):
        return cal
    return StereoCalibration.synthetic()


def marker_locator(setup: SetupConfig, camera: object) -> StereoMarkerLocator:
    """The controller's marker locator on the setup's calibration: region-of-interest tracking
    when ``[procedure.vision] roi_tracking`` (the default), else a full-frame search per pair."""
    v = setup.procedure.vision
    loc = StereoMarkerLocator(_calibration(setup, camera))
    if v.roi_tracking and isinstance(loc, _Locator):  # (tests may substitute their own locator)
        loc.use_tracking(TrackingParams(window_margin_px=v.window_margin_px,
                                        reacquire_every=v.reacquire_every_frames,
                                        lost_retry_every=v.lost_retry_every_frames))
    return loc


def _needle_checker(setup: SetupConfig,
                    camera: object) -> StereoNeedleChecker | CollinearNeedleChecker | None:
    """The seed-004 needle-axis check when ``[procedure.lock.needle_check]`` is set, else None:
    contour lines (``method = "cylinder"``) or collinear beads (``method = "collinear"``)."""
    nc = setup.procedure.lock.needle_check
    if nc is None:
        return None
    if nc.method == "collinear":
        return CollinearNeedleChecker(_calibration(setup, camera), nc.bead_positions_mm(),
                                      nc.max_mono_stereo_deg)
    return StereoNeedleChecker(_calibration(setup, camera), nc.radius_mm)


#: Takes the robot driver the setup built (CONFIGURED, not opened) and returns the robot the
#: controller commands instead -- a recording, checking or fault-injecting wrapper. The wrapper
#: owns the inner driver's lifecycle: its ``open``/``close`` open and close the inner one.
RobotWrapper = Callable[[Robot], Robot]


def wrap_robot(devices: Devices, wrapper: RobotWrapper) -> Devices:
    """``devices`` (not opened) with the robot replaced by ``wrapper(devices.robot)``; open and
    close the result (``open_all``/``close_all``) instead of the original."""
    return dataclasses.replace(devices, robot=wrapper(devices.robot))


def build_controller(setup: SetupConfig, plan: ProcedurePlan, devices: Devices, *, clock: Clock,
                     session: SessionLog, operator: Operator,
                     observers: Sequence[TickObserver] = (), hooks: HookCaller | None = None) -> Controller:
    """The controller ``hil run`` builds for ``setup`` on ``devices`` (ACTIVE, or opened before
    :meth:`Controller.run`): marker locator on the setup's stereo calibration, rig geometry,
    procedure, ``[safety]`` limits and watchdog ages, the simulated world as breath-hold coach and
    ground truth when there is one, the needle-axis check when configured. To command the robot
    through a wrapper, build ``devices`` with :func:`wrap_robot` first. Raises what the
    calibration loader raises (InputFileError) for a bad calibration file."""
    sf = setup.safety
    devices = with_rig_time_offsets(setup, devices)  # [calibration] rig: stamps at the true times
    world = devices.world
    return Controller(
        camera=devices.camera, robot=devices.robot, tracker=devices.tracker, clock=clock,
        locate=marker_locator(setup, devices.camera), plan=plan, rig=_rig(setup),
        procedure=setup.procedure, limits=sf.motion_limits(),
        watchdog_ages_s={"camera": sf.camera_frame_max_age_ms / 1e3,
                         "robot": sf.robot_state_max_age_ms / 1e3,
                         "tracker": sf.tracker_max_age_ms / 1e3},
        session=session, operator=operator,
        coach=world if isinstance(world, BreathHoldCoach) else None,
        truth=world if isinstance(world, GroundTruth) else None,
        needle_check=_needle_checker(setup, devices.camera),
        observers=observers, hooks=hooks,
        tracker_use=_tracker_use(setup, world is not None),
    )


def _tracker_use(setup: SetupConfig, simulated_world: bool) -> TrackerUse | None:
    """The tracker's part in the procedure (``[procedure.tracking]``), or None when no sensor is
    configured for use or the setup has no tracker. The tracker registration comes from
    ``calibration`` (a ``hil tracker-calibrate`` file); a simulated setup without one uses its
    own transmitter mounting (``[simulation] T_optical_from_tracker``).

    Raises:
        InputFileError: no usable tracker registration.
        CalibrationError: the calibration file is malformed.
    """
    tc = setup.procedure.tracking
    if setup.tracker is None or (tc.needle_sensor is None and tc.reference_sensor is None):
        return None
    if tc.calibration is not None:
        path = Path(tc.calibration)
        if not path.is_absolute():
            path = setup.config_dir / path
        _, T = load_tracker_calibration(path)
        if T is None:
            raise InputFileError(str(path), "no registration (T_optical_from_tracker): run "
                                            "hil tracker-calibrate with stylus touches")
    elif simulated_world:
        T = setup.simulation.T_optical_from_tracker.as_transform()
    else:
        raise InputFileError("[procedure.tracking]", "uses tracker sensors but names no calibration "
                                                     "(the tracker registration)")
    return TrackerUse(tc, T)


def _start_igtl(setup: SetupConfig, clock: Clock) -> IgtlServer | None:
    """The read-only OpenIGTLink server of ``[igtl]`` when enabled (started), else None.

    Raises:
        IgtlError: the port cannot be bound, or the ``igtl`` extra (pyigtl) is missing.
    """
    if not setup.igtl.enabled:
        return None
    from hil.igtl.server import IgtlServer

    server = IgtlServer(setup.igtl, clock)
    server.start()
    return server


def runtime_plugins(igtl: IgtlServer | None, plan: ProcedurePlan) -> HilPlugins:
    """The installed plugins (entry points: their ``hil_on_tick`` / ``hil_on_transition`` see the
    run) plus, when the OpenIGTLink server runs, the built-in stream on the same hooks."""
    plugins = HilPlugins()
    if igtl is not None:
        from hil.igtl.plugin import PLUGIN_NAME, IgtlPlugin

        plugins.register(IgtlPlugin(igtl, plan), PLUGIN_NAME)
    return plugins


def run_procedure(config_path: Path, setup: SetupConfig, plan: ProcedurePlan, *, auto: bool,
                  session_dir: Path, max_duration_s: float | None = None,
                  clock: Clock | None = None, operator: Operator | None = None,
                  robot_wrapper: RobotWrapper | None = None) -> RunSummary:
    """Build the devices of ``setup``, run the procedure, close everything; return the summary.

    Simulated setups run on a :class:`ManualClock` (faster than real time) unless
    ``[simulation] real_time``; other setups on the monotonic clock. ``operator`` overrides the
    auto / interactive operator chosen by ``auto``. ``robot_wrapper`` (see :data:`RobotWrapper`)
    puts a wrapper between the controller and the robot driver.
    """
    if clock is None:
        from plugins.manager import default_registry

        reg = default_registry()
        simulated = any(reg.get(role, str(getattr(cfg, "driver", ""))).simulated
                        for role, cfg in setup.device_sections().items())
        fast = simulated and not setup.simulation.real_time
        clock = ManualClock(1_000_000_000) if fast else MonotonicClock()
    devices = build_devices(setup, clock)
    if robot_wrapper is not None:
        devices = wrap_robot(devices, robot_wrapper)
    world = devices.world
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%S%fZ")
    header: dict[str, Any] = {
        "setup": str(config_path), "setup_name": setup.name,
        "config_sha256": file_sha256(config_path),
        "resolved_setup_sha256": hashlib.sha256(
            json.dumps(setup.resolved(), sort_keys=True, default=str).encode()).hexdigest(),
        "plan": plan.source,
        "plan_sha256": file_sha256(plan.source) if Path(plan.source).is_file() else None,
        "calibration": str(setup.calibration.stereo) if setup.calibration.stereo else None,
        "calibration_sha256": file_sha256(setup.calibration.stereo) if setup.calibration.stereo else None,
        "rig_calibration": str(setup.calibration.rig) if setup.calibration.rig else None,
        "rig_calibration_sha256": rig_calibration_sha256(setup),
        "seed": setup.simulation.seed if world is not None else None,
        "procedure": setup.procedure.model_dump(mode="json"), "auto": auto,
    }
    igtl = _start_igtl(setup, clock)  # first: a busy port is a usage error, nothing else started
    try:
        session = SessionLog(session_dir / f"session_{stamp}.jsonl", clock, header)
        devices.open_all()
    except BaseException:
        if igtl is not None:
            igtl.close()
        raise
    try:
        ctl = build_controller(
            setup, plan, devices, clock=clock, session=session,
            operator=operator or (AutoOperator() if auto else InteractiveOperator()),
            hooks=runtime_plugins(igtl, plan),
        )
        summary = ctl.run(max_duration_s)
        if isinstance(ctl.locate, _Locator):
            summary.locate_ms = ctl.locate.locate_ms()
    finally:
        devices.close_all()
        if igtl is not None:
            igtl.close()
    session.close(final_state=summary.final_state, states=summary.states)
    summary.session_log_sha256 = session.head_sha256  # the chain head, published outside the file
    return summary


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
                            max_duration_s=args.max_duration)
    if not args.no_report:
        summary.report = build_session_report(summary.session_log, sys.stderr)
    if args.json:
        sys.stdout.write(json.dumps(summary.to_dict(), default=str) + "\n")
    else:
        print_text(summary, sys.stdout)
    return 0 if summary.final_state == State.DONE.value else 1

