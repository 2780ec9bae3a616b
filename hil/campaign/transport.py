"""The transport tier of the campaign: faults that live in a transport, on the REAL drivers against
their emulators (docs/campaign.md, "Transport tier").

Each run starts its emulator as a subprocess (the UR emulator on a private loopback address, the
Flock of Birds emulator on a pty), writes a mixed setup to the run's directory (simulated camera
and world; the real ``ur_rtde`` robot driver and/or the real ``fob`` or ``aurora`` tracker driver on
the emulator), and runs the procedure in real time, bounded. The fault is **state-triggered**: the
operator sends it through the emulator's fault channel ``delay_s`` after the controller entered
the target state (and, from then on, holds any pending confirmation until the fault is over, so a
fault aimed at COMPENSATE or LOCK lands there however fast the machine is). The run is judged with the
same criteria as the simulator tier (:func:`hil.campaign.runner.judge`).
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import time
import traceback
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from hil.clock import Clock, MonotonicClock
from hil.config import Devices, build_devices, load_setup
from hil.config.faults import FAULT_DEVICE, FaultKind
from hil.config.setup import SetupConfig
from hil.controller.fsm import Event, State
from hil.controller.operator_input import OperatorView
from hil.controller.plan_file import load_plan
from hil.errors import HilError
from hil.session.log import SessionLog, file_sha256

from . import gige
from .emulators import (
    CONFIGS_DIR,
    EmulatorError,
    start_trackersim,
    start_ursim,
    trackersim_command,
    ursim_command,
)
from .operator import HALTED, CampaignOperator
from .pool import Progress, run_parallel
from .recorder import Recording, RecordingRobot
from .report import family_of, render_html, summarise, table
from .runner import RECOVER_SETTLE_S, RunResult, RunSpec, _latency_bound_ms, judge, state_path
from .scenarios import TARGET_STATES, ScenarioSelectionError

Emulator = Literal["ursim", "trackersim", "fakegv"]
TrackerProtocol = Literal["fob", "aurora"]

#: Watchdog ages for the real-time runs (ms / s): a loaded shared 2-core machine pauses the
#: simulated camera and the emulators for a few 100 ms; the faults under test are detected from
#: the robot's safety status, the link state and the tracker driver's own errors.
REAL_TIME_WATCHDOGS: dict[str, float] = {
    "camera_frame_max_age_ms": 1500.0,
    "tracker_max_age_ms": 1000.0,
    "robot_state_max_age_ms": 1000.0,
}
#: How long no stereo pair may arrive in the real-time runs whose fault is not the camera's (ms):
#: as long as the camera's loosened age. The default (4 frame periods, 267 ms at 15 Hz) faulted
#: runs in CI whose camera pipeline a host taking 30 % of each vCPU had slowed below 4 pairs/s,
#: while the camera's age bound above allowed 1.5 s. The camera scenario keeps the default: there
#: the camera is the device under test.
REAL_TIME_CAMERA_SILENCE_MS = 1500.0
#: The UR driver's stale-stream limit in the transport runs (s; configs/sim_ursim.toml has 1.0).
URSIM_STATE_MAX_AGE_S = 0.5
#: Procedure time bound of one transport run (s); clean runs take ~15-30 s.
TRANSPORT_MAX_DURATION_S = 60.0
#: Wall-time bound of one transport run, emulator start excluded (s).
TRANSPORT_TIMEOUT_S = 150.0
CONFIRM = ("plan_to_approach", "compensate_to_lock", "lock_to_done")


@dataclass(frozen=True)
class TransportFault:
    """A fault family sent through an emulator's fault channel (one row of the transport matrix).

    ``kind`` is the symptom the controller sees (its profile gives the latency bound and how it
    becomes detectable); ``inject`` and ``clear`` are the fault-channel lines sent at onset and at
    the end of the window (None: the emulator ends it by itself, or nothing needs ending).
    """

    family: str
    emulator: Emulator
    kind: FaultKind
    inject: str
    clear: str | None
    duration_s: float
    base: str  # setup the mixed setup is written from, relative to configs/
    what: str  # one line for the docs and the table legend
    protocol: TrackerProtocol = "fob"  # trackersim rows: the device emulated and the driver used


@dataclass(frozen=True)
class TransportScenario:
    """A transport fault aimed at a workflow state: ``<family>@<state>``, sent ``delay_s`` after
    the controller first entered ``state``."""

    name: str
    emulator: Emulator
    kind: FaultKind
    state: str
    inject: str
    clear: str | None
    duration_s: float
    delay_s: float
    base: str  # setup the mixed setup is written from, relative to configs/
    protocol: TrackerProtocol = "fob"

    @property
    def device(self) -> str:
        return FAULT_DEVICE[self.kind]

    @property
    def family(self) -> str:
        return self.name.partition("@")[0]


#: Every fault the emulators' fault channels can play (docs/ursim.md, docs/trackers.md), as the
#: symptom kind the controller sees. RTDE faults go to ``tools/ursim`` and the ``ur_rtde`` driver,
#: serial faults to ``tools/trackersim`` (Flock of Birds on a pty) and the ``fob`` driver, Aurora
#: faults to ``tools/trackersim --protocol aurora`` and the ``aurora`` driver (the reference sensor
#: in use, :data:`AURORA_PROCEDURE_TRACKING`), camera
#: faults to ``tools/fakegv`` (two fake GigE cameras serving the simulated world) and the ``aravis``
#: driver, inside the run's own network namespace (:mod:`hil.campaign.gige`).
TRANSPORT_FAULTS: tuple[TransportFault, ...] = (
    TransportFault("rtde_protective_stop", "ursim", FaultKind.PROTECTIVE_STOP, "protective_stop", None, 0.5,
                   "sim_ursim.toml", "the controller raises a protective stop (cleared by recover())"),
    TransportFault("rtde_estop", "ursim", FaultKind.PROTECTIVE_STOP, "estop", "release", 1.0,
                   "sim_ursim.toml", "emergency stop pressed, released after the window"),
    TransportFault("rtde_drop_connection", "ursim", FaultKind.ROBOT_DISCONNECT, "drop_connection 1.0", None,
                   1.0, "sim_ursim.toml", "every RTDE/dashboard connection dropped, ports closed for 1 s"),
    TransportFault("rtde_pause_stream", "ursim", FaultKind.ROBOT_DISCONNECT, "pause_stream 1.5", None, 1.5,
                   "sim_ursim.toml", "the RTDE output stream goes silent for 1.5 s (link up, no data)"),
    TransportFault("rtde_stop_program", "ursim", FaultKind.MOTION_REJECTED, "stop_program", None, 0.5,
                   "sim_ursim.toml", "the control script stops (as from the pendant)"),
    TransportFault("rtde_slow_responses", "ursim", FaultKind.MOTION_LAG, "slow_responses 200",
                   "slow_responses 0", 1.5, "sim_ursim.toml", "every reply and command 200 ms late"),
    TransportFault("rtde_stall", "ursim", FaultKind.MOTION_LAG, "stall on", "stall off", 1.5,
                   "sim_ursim.toml", "the arm stops following its targets (drive stall)"),
    TransportFault("serial_garbage", "trackersim", FaultKind.CORRUPT_RECORD, "fault garbage,p=1",
                   "clear garbage", 0.6, "sim.toml", "random bytes inserted into every record"),
    TransportFault("serial_truncate", "trackersim", FaultKind.CORRUPT_RECORD, "fault truncate,p=1",
                   "clear truncate", 0.6, "sim.toml", "the tail of every record dropped"),
    TransportFault("serial_lost_phase", "trackersim", FaultKind.CORRUPT_RECORD, "fault lost_phase,p=1",
                   "clear lost_phase", 0.6, "sim.toml", "the phasing bit of every record cleared"),
    TransportFault("serial_wrong_baud", "trackersim", FaultKind.CORRUPT_RECORD,
                   "fault wrong_baud,baud=9600", "clear wrong_baud", 0.6, "sim.toml",
                   "the bird switches to 9600 baud (host stays at 115200)"),
    TransportFault("serial_silence", "trackersim", FaultKind.TRACKER_TIMEOUT, "fault silence,seconds=1.0",
                   None, 1.0, "sim.toml", "the bird sends nothing for 1 s"),
    TransportFault("aurora_bad_crc", "trackersim", FaultKind.CORRUPT_RECORD, "fault bad_crc,p=1",
                   "clear bad_crc", 0.6, "sim.toml", "the CRC of every Aurora reply wrong", "aurora"),
    TransportFault("aurora_tool_missing", "trackersim", FaultKind.SENSOR_MISSING,
                   "fault tool_missing,handles=0A", "clear tool_missing", 1.0, "sim.toml",
                   "the reference tool (handle 0A) not seen: MISSING for 1 s", "aurora"),
    TransportFault("aurora_out_of_volume", "trackersim", FaultKind.SENSOR_MISSING,
                   "fault out_of_volume,handles=0A", "clear out_of_volume", 1.0, "sim.toml",
                   "the reference tool (handle 0A) out of the volume (port status 0x40) for 1 s", "aurora"),
    TransportFault("aurora_reset", "trackersim", FaultKind.TRACKER_TIMEOUT, "fault reset", None, 1.5,
                   "sim.toml", "the Aurora resets mid-tracking: RESET at 9600, not tracking", "aurora"),
    TransportFault("aurora_wrong_baud", "trackersim", FaultKind.TRACKER_TIMEOUT,
                   "fault wrong_baud,baud=9600", "clear wrong_baud", 0.6, "sim.toml",
                   "the Aurora leaves the COMM rate for 9600 baud (host stays at 115200)", "aurora"),
    TransportFault("aurora_comm_baud", "trackersim", FaultKind.TRACKER_TIMEOUT,
                   "fault comm_baud,baud=57600; fault reset", None, 3.0, "sim.toml",
                   "the Aurora resets, and the driver's next COMM leaves it at 57600 (host at 115200)",
                   "aurora"),
    TransportFault("camera_stream_loss", "fakegv", FaultKind.FRAME_DROP, "stream_loss 1.0", None, 1.0,
                   "sim.toml", "both GigE cameras silent (GVCP, GVSP), back on the same addresses after 1 s"),
)

#: Workflow states the transport matrix aims at (the simulator tier's), and how long after
#: entering each the fault is sent (s): early enough that the state has not ended on a fast run
#: (the operator holds the state's outgoing confirmation, where it has one, until recovery is due).
TRANSPORT_STATES: tuple[str, ...] = TARGET_STATES
TRANSPORT_DELAY_S: dict[str, float] = {"register": 0.2, "approach": 0.3, "gate": 0.2, "compensate": 1.5,
                                       "lock": 0.5}

FAMILIES: tuple[str, ...] = tuple(f.family for f in TRANSPORT_FAULTS)
TRANSPORT_SCENARIOS: tuple[TransportScenario, ...] = tuple(
    TransportScenario(f"{f.family}@{state}", f.emulator, f.kind, state, f.inject, f.clear, f.duration_s,
                      TRANSPORT_DELAY_S[state], f.base, f.protocol)
    for f in TRANSPORT_FAULTS for state in TRANSPORT_STATES
)
BY_NAME = {s.name: s for s in TRANSPORT_SCENARIOS}


def select_transport(patterns: list[str]) -> list[TransportScenario]:
    """Transport scenarios matching any pattern ``FAMILY[@STATE]`` (shell wildcards; FAMILY may be
    any prefix of a family name: ``serial`` = every serial family in every state, ``rtde@register``
    = every RTDE family in REGISTER, ``@lock`` = every family in LOCK).
    No pattern: the whole matrix (every family x every state).

    Raises:
        ScenarioSelectionError: a pattern matches nothing (names the choices).
    """
    import fnmatch

    if not patterns:
        return list(TRANSPORT_SCENARIOS)
    chosen: list[TransportScenario] = []
    for pat in patterns:
        family, _, state = pat.partition("@")
        if not any(c in family for c in "*?["):
            family += "*"  # a family name or any prefix of one (``rtde``, ``serial_g``)
        full = f"{family}@{state or '*'}"
        hit = [s for s in TRANSPORT_SCENARIOS if fnmatch.fnmatchcase(s.name, full)]
        if not hit:
            raise ScenarioSelectionError(
                f"transport scenario {pat!r} matches nothing (FAMILY@STATE; families: "
                f"{', '.join(f.family for f in TRANSPORT_FAULTS)}; states: {', '.join(TRANSPORT_STATES)})")
        chosen += [s for s in hit if s not in chosen]
    return chosen


# ---------------------------------------------------------------------- the mixed setup
#: The Aurora rows' reference-sensor use (appended after ``[procedure]``): the patient reference on
#: handle 0A stands in for the skin markers when they give no rigid change and is checked against
#: them otherwise (docs/run.md, "The tracker"); the transmitter mounting is the simulated world's.
AURORA_PROCEDURE_TRACKING = '\n[procedure.tracking]\nreference_sensor = "reference"\n'


def aurora_tracker_section(port: str) -> str:
    """The ``[tracker]`` of an Aurora row: the real ``aurora`` driver on the emulator's pty at
    115200 after COMM, the two wired tools (reference 0A, needle 0B), the break sent as a NUL (a
    pty has none), short reply and reset timeouts (a pty answers at once), re-initialisation after
    1 s without an answer."""
    return (f'[tracker]\ndriver = "aurora"\nport = "{port}"\nbaud_rate = 115200\n'
            'sensors = { reference = "0A", needle = "0B" }   # the emulator\'s two wired tools\n'
            'break_as_nul = true\nreset_timeout_s = 2.0\nresponse_timeout_s = 0.3\ntimeout_s = 0.5\n'
            "reinit_after_s = 1.0\n\n")


def _set_key(text: str, key: str, value: str) -> str:
    text, n = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.MULTILINE)
    if n != 1:
        raise HilError(f"transport setup: key {key!r} not found in the base setup")
    return text


def _add_key_after(text: str, after: str, key: str, value: str) -> str:
    """``key = value`` on the line after the ``after = ...`` line (which must be there)."""
    text, n = re.subn(rf"^({after} = .*)$", lambda m: f"{m.group(1)}\n{key} = {value}", text, count=1,
                      flags=re.MULTILINE)
    if n != 1:
        raise HilError(f"transport setup: key {after!r} not found in the base setup")
    return text


def write_setup(sc: TransportScenario, out: Path, *, seed: int, ursim_host: str | None = None,
                tracker_port: str | None = None) -> Path:
    """Write the mixed setup of one run to ``out/setup.toml`` (from ``configs/<sc.base>``)."""
    base = CONFIGS_DIR / sc.base
    text = base.read_text()
    text = re.sub(r'^stereo = "(.*)"$', lambda m: f'stereo = "{(base.parent / m.group(1)).resolve()}"',
                  text, count=1, flags=re.MULTILINE)
    text = _set_key(text, "real_time", "true")
    text = _set_key(text, "seed", str(seed))
    text = _set_key(text, "max_duration_s", str(TRANSPORT_MAX_DURATION_S))
    for key, value in REAL_TIME_WATCHDOGS.items():
        text = _set_key(text, key, str(value))
    if sc.device != "camera":
        text = _add_key_after(text, "camera_frame_max_age_ms", "camera_silence_ms",
                              str(REAL_TIME_CAMERA_SILENCE_MS))
    text = text.replace("[procedure]\n", "[procedure]\nconfirm = [" + ", ".join(f'"{c}"' for c in CONFIRM)
                        + "]\n", 1)
    if ursim_host is not None:
        text = text.replace('host = "127.0.0.1"', f'host = "{ursim_host}"')  # robot and [fault_channel]
        # the driver's own stale-stream limit, under the controller's loosened robot watchdog: a
        # stalled RTDE stream (rtde_pause_stream) is detected by the driver, well inside the bound
        text = _set_key(text, "state_max_age_s", str(URSIM_STATE_MAX_AGE_S))
    if tracker_port is not None:
        start = text.index("[tracker]\n")
        end = text.index("[calibration]\n")
        if sc.protocol == "aurora":
            text = (text[:start] + aurora_tracker_section(tracker_port) + text[end:]
                    + AURORA_PROCEDURE_TRACKING)
        else:
            fob = (f'[tracker]\ndriver = "fob"\nport = "{tracker_port}"\nbaud_rate = 115200\n'
                   "sensors = { reference = 0 }   # the emulator's standalone bird\n\n")
            text = text[:start] + fob + text[end:]
    path = out / "setup.toml"
    head = f"# transport campaign run: {sc.name}, seed {seed} (written by hil campaign --transport)\n"
    path.write_text(head + text)
    return path


def write_gige_setup(sc: TransportScenario, out: Path, *, seed: int) -> Path:
    """Write the camera run's mixed setup to ``out/setup.toml``: :func:`write_setup`'s real-time
    transport setup from ``configs/<sc.base>`` (simulated robot, tracker and world) with its
    ``[camera]`` replaced by :func:`hil.campaign.gige.aravis_camera_section`."""
    path = write_setup(sc, out, seed=seed)
    text = path.read_text()
    section = gige.aravis_camera_section(load_setup(path))
    text, n = re.subn(r"^\[camera\]\n.*?(?=^\[)", lambda _m: section, text, count=1,
                      flags=re.MULTILINE | re.DOTALL)
    if n != 1:
        raise EmulatorError(f"{path}: no [camera] section to replace")
    path.write_text(text)
    return path


# ---------------------------------------------------------------------- the operator
class TransportOperator(CampaignOperator):
    #: recovery attempts before the fault is sent, and again for the fault
    MAX_RECOVERIES = 2

    """The campaign operator plus a state trigger: ``delay_s`` after the controller first entered
    ``target``, it calls ``inject`` (sends the fault through the emulator) and records the onset on
    ``clock``; at the end of the window it calls ``clear``. Once the target state was entered it
    holds every pending confirmation (``compensate_to_lock``, ``lock_to_done``, ...) until the fault
    is over and the recovery time has come, so the procedure cannot leave the target state early.
    A halt before the fault is sent (a fault on the way to the target state: the procedure never
    gets there unless someone recovers it) is recovered as an operator would, once the robot had
    :data:`RECOVER_SETTLE_S` to stop: resume, or reset and start again when there is no plan to
    resume (at most ``max_recoveries`` times before the fault; the fault then gets as many again).
    Operator commands are recorded in seconds since ``t0_ns`` (the session log's start), the time
    base :func:`judge` uses."""

    def __init__(self, target: str, delay_s: float, duration_s: float, clock: Clock, t0_ns: int,
                 inject: Callable[[], object], clear: Callable[[], object] | None) -> None:
        super().__init__(recover_after_s=math.inf, max_recoveries=self.MAX_RECOVERIES)
        self.target, self.delay_s, self.duration_s = target, delay_s, duration_s
        #: controller time the procedure halted before the fault was sent (None: not halted)
        self._halted_since_s: float | None = None
        self.clock, self.t0_ns = clock, t0_ns
        self._inject, self._clear = inject, clear
        self.entered_s: float | None = None
        self.fired_view_s: float | None = None
        self.onset_s: float | None = None  # since t0_ns
        self.cleared = False
        self.inject_error: str | None = None

    def _since_t0(self) -> float:
        return (self.clock.now_ns() - self.t0_ns) * 1e-9

    def _send(self, view: OperatorView, ev: Event) -> Event:
        self._last, self._last_state = ev, view.state
        self.commands.append((round(self._since_t0(), 4), ev.value))
        return ev

    def _before_the_fault(self, view: OperatorView) -> None:
        """Before the fault is sent: recovery is due :data:`RECOVER_SETTLE_S` after the procedure
        halted (never while it is under way)."""
        if view.state in HALTED or (view.state is State.IDLE and self._started):
            if self._halted_since_s is None:
                self._halted_since_s = view.t_s
            self.recover_after_s = self._halted_since_s + RECOVER_SETTLE_S
        else:
            self._halted_since_s, self.recover_after_s = None, math.inf

    def poll(self, view: OperatorView) -> Event | None:
        if self.fired_view_s is None:
            self._before_the_fault(view)
            if self.entered_s is None and view.state.value == self.target:
                self.entered_s = view.t_s
            if self.entered_s is not None and view.t_s >= self.entered_s + self.delay_s:
                self.onset_s = self._since_t0()
                self.fired_view_s = view.t_s
                self.recover_after_s = view.t_s + self.duration_s + RECOVER_SETTLE_S
                self.recoveries_left = self.MAX_RECOVERIES
                try:
                    self._inject()
                except EmulatorError as exc:
                    self.inject_error = str(exc)
        elif not self.cleared and view.t_s >= self.fired_view_s + self.duration_s:
            self.cleared = True
            if self._clear is not None:
                try:
                    self._clear()
                except EmulatorError as exc:
                    self.inject_error = str(exc)
        if view.pending is not None and self.entered_s is not None and (
                self.fired_view_s is None or view.t_s < self.recover_after_s):
            return None  # stay in the target state until the fault has come and gone
        return super().poll(view)


class GigeOperator(TransportOperator):
    """The transport operator, recovering :data:`hil.campaign.gige.GIGE_RECOVER_EXTRA_S` later
    (see there)."""

    def poll(self, view: OperatorView) -> Event | None:
        fired = self.fired_view_s is not None
        ev = super().poll(view)
        if not fired and self.fired_view_s is not None:
            self.recover_after_s += gige.GIGE_RECOVER_EXTRA_S
        return ev


# ---------------------------------------------------------------------- one run
@dataclass(frozen=True)
class TransportSpec:
    """One transport run (picklable: it crosses to the run's process)."""

    run_id: str
    scenario: str
    seed: int
    setup: str
    plan: str
    log_dir: str
    ursim_host: str | None = None
    tracker_control: str | None = None
    max_duration_s: float = TRANSPORT_MAX_DURATION_S

    # the pool reports these for a hang / a dead process
    @property
    def kind(self) -> str:
        return BY_NAME[self.scenario].kind.value

    @property
    def state(self) -> str:
        return BY_NAME[self.scenario].state


def run_transport_one(spec: TransportSpec) -> RunResult:
    """Run and judge one transport run (in the run's process; the emulator already runs, except for
    the camera runs, which start theirs inside the run: :func:`run_gige_one`)."""
    sc = BY_NAME[spec.scenario]
    if sc.emulator == "fakegv":
        return run_gige_one(spec)
    host, control = spec.ursim_host, spec.tracker_control

    def send(line: str) -> object:
        if sc.emulator == "ursim":
            assert host is not None
            return ursim_command(host, line)
        assert control is not None
        return trackersim_command(Path(control), line)

    return run_judged(spec, send)


#: ``(setup, devices, clock) -> context``: what a run needs around its devices (entered before they
#: are opened, left after they are closed), e.g. emulators started inside the run's process.
Around = Callable[[SetupConfig, Devices, Clock], AbstractContextManager[None]]


def run_judged(spec: TransportSpec, send: Callable[[str], object], *,
               operator_type: type[TransportOperator] = TransportOperator,
               around: Around | None = None) -> RunResult:
    """Run and judge one transport run in this process: the setup's devices (the robot behind a
    :class:`RecordingRobot`), ``around`` (if any) around them, the controller with a
    state-triggered ``operator_type`` that sends the fault lines with ``send``. Never raises for a
    controller, driver or emulator problem (it fails the run)."""
    from hil.controller.assembly import build_controller, wrap_robot

    t_wall = time.perf_counter()
    sc = BY_NAME[spec.scenario]
    setup = load_setup(spec.setup)
    plan = load_plan(Path(spec.plan))
    clock = MonotonicClock()
    limits = setup.safety.motion_limits()
    log_path = Path(spec.log_dir) / f"{spec.run_id}.jsonl"
    log_path.unlink(missing_ok=True)
    clear_line = sc.clear
    t0_ns = clock.now_ns()
    session = SessionLog(log_path, clock, {
        "setup": spec.setup, "config_sha256": file_sha256(spec.setup), "campaign_run": spec.run_id,
        "scenario": sc.name, "tier": "transport", "seed": spec.seed, "fault_kind": sc.kind.value,
        "fault_transport": sc.inject, "fault_state": sc.state, "fault_delay_s": sc.delay_s,
        "fault_duration_s": sc.duration_s,
    })
    operator = operator_type(sc.state, sc.delay_s, sc.duration_s, clock, t0_ns,
                             inject=lambda: send(sc.inject),
                             clear=None if clear_line is None else (lambda: send(clear_line)))
    result = RunResult(spec.run_id, sc.name, sc.kind.value, sc.state, spec.seed, passed=False,
                       session_log=str(log_path))
    closed: dict[str, Any] = {}
    devices = None
    frame_rate = 15.0
    try:
        devices = wrap_robot(build_devices(setup, clock), lambda robot: RecordingRobot(robot, limits, clock))
        with around(setup, devices, clock) if around is not None else contextlib.nullcontext():
            try:
                devices.open_all()
                frame_rate = devices.camera.frame_rate_hz
                ctl = build_controller(setup, plan, devices, clock=clock, session=session, operator=operator)
                summary = ctl.run(spec.max_duration_s)
            finally:
                devices.close_all()
        result.final_state = summary.final_state
        result.lock_error_mm = summary.lock_error_mm
        result.duration_s = round(summary.duration_s, 4)
        closed = {"final_state": summary.final_state}
    except EmulatorError as exc:  # an emulator started around the devices did not come up
        result.reasons.append(f"emulator: {exc}")
        result.outcome = "crashed"
        closed = {"final_state": "crashed", "error": f"emulator: {exc}"}
    except Exception as exc:  # noqa: BLE001 - a controller or driver crash is a finding
        result.error = "".join(traceback.format_exception(exc))[-4000:]
        closed = {"final_state": "crashed", "error": f"{type(exc).__name__}: {exc}"}
    finally:
        session.close(**closed)
    recorder = devices.robot if devices is not None else None
    assert recorder is None or isinstance(recorder, RecordingRobot)
    result.latency_bound_ms = _latency_bound_ms(setup, sc.device, frame_rate)
    onset = operator.onset_s
    run_spec = RunSpec(spec.run_id, spec.setup, spec.plan, spec.seed, kind=sc.kind.value, state=sc.state,
                       start_s=onset if onset is not None else 1e9, duration_s=sc.duration_s)
    out = judge(run_spec, result, recorder.recording if recorder else Recording(), log_path, operator)
    if onset is None:
        out.onset_s = None
        out.reasons[:] = [r for r in out.reasons if "before the fault" not in r]
        out.reasons.append(f"the run never stayed {sc.delay_s} s in {sc.state}: fault not sent "
                           f"(states: {state_path(log_path)})")
        out.passed = False
    elif out.state_at_onset != sc.state:  # the matrix cell was not tested: the state ended first
        out.reasons.append(f"fault sent in {out.state_at_onset}, not in {sc.state} "
                           f"(left it within {sc.delay_s} s)")
        out.passed = False
    if operator.inject_error is not None:
        out.reasons.append(f"fault channel: {operator.inject_error}")
        out.passed = False
    _stopped_after_link_back(out, recorder.recording if recorder else Recording(), log_path, operator)
    out.wall_s = round(time.perf_counter() - t_wall, 3)
    return out


def run_gige_one(spec: TransportSpec) -> RunResult:
    """Run and judge one camera run (in the run's process, spawned by the pool): enter a private
    network namespace, then start the simulated camera, its pump and fakegv around the procedure
    (:func:`hil.campaign.gige.gige_rig`). Not runnable here (not root): a failed result whose one
    reason says why."""
    sc = BY_NAME[spec.scenario]
    try:
        why = gige.why_not_runnable()
        if why is not None:
            raise EmulatorError(why)
        gige.enter_private_netns()
    except EmulatorError as exc:
        return RunResult(spec.run_id, sc.name, sc.kind.value, sc.state, spec.seed, passed=False,
                         outcome="not_runnable", reasons=[f"not runnable here: {exc}"])
    rig = gige.GigeRig(Path(spec.log_dir) / spec.run_id)
    return run_judged(spec, rig.send, operator_type=GigeOperator,
                      around=lambda setup, devices, clock: gige.gige_rig(rig, setup, devices, clock))


def _stopped_after_link_back(out: RunResult, rec: Any, log_path: Path, operator: TransportOperator) -> None:
    """A dropped RTDE link gives no robot states until ``recover()`` rebuilds the clients, so the
    robot cannot be *seen* stopped before recovery: accept the first state read after the
    recovery command instead (before any motion command), when it shows the arm at rest."""
    from .runner import STOPPED_MM_S

    if out.kind != FaultKind.ROBOT_DISCONNECT.value:
        return
    missing = [r for r in out.reasons if r.startswith("robot not seen stopped")]
    if not missing or out.safe_state is None or out.state_windows_s is None:
        return
    first = json.loads(log_path.read_text().splitlines()[0])
    t0 = int(first["t_ns"])
    t_safe = next((t for t, s in _entered(log_path, t0) if s == out.safe_state and
                   out.onset_s is not None and t >= out.onset_s), None)
    if t_safe is None:
        return
    t_rec = next((t for t, _c in operator.commands if t >= t_safe), None)
    if t_rec is None:
        return
    first_cmd = next(((c.t_ns - t0) * 1e-9 for c in rec.commands
                      if c.kind != "stop" and (c.t_ns - t0) * 1e-9 >= t_rec), math.inf)  # a motion command
    states = [s for s in rec.states if t_rec <= (s.t_ns - t0) * 1e-9 <= first_cmd]
    if states and states[0].speed_mm_s < STOPPED_MM_S:
        out.reasons[:] = [r for r in out.reasons if r not in missing]
        out.stop_latency_ms = round(((states[0].t_ns - t0) * 1e-9 - t_safe) * 1e3, 3)
        out.passed = not out.reasons


def _entered(log_path: Path, t0: int) -> list[tuple[float, str]]:
    out = []
    for line in log_path.read_text().splitlines():
        r = json.loads(line)
        if r.get("event") == "state_entered":
            out.append(((int(r["t_ns"]) - t0) * 1e-9, str(r.get("state"))))
    return out


# ---------------------------------------------------------------------- the campaign
@dataclass
class _Prepared:
    spec: TransportSpec
    stop: Callable[[], None]


def _prepare(sc: TransportScenario, seed: int, logs: Path) -> _Prepared:
    """Start the run's emulator and write its mixed setup. Raises EmulatorError."""
    run_id = f"{sc.name}_s{seed}"
    run_dir = logs / run_id
    run_dir.mkdir(parents=True, exist_ok=True)
    if sc.emulator == "fakegv":  # started by the run itself, inside its network namespace
        setup = write_gige_setup(sc, run_dir, seed=seed)
        return _Prepared(TransportSpec(run_id, sc.name, seed, str(setup), str(_plan(sc)), str(logs)),
                         lambda: None)
    if sc.emulator == "ursim":
        ursim = start_ursim(run_dir)
        setup = write_setup(sc, run_dir, seed=seed, ursim_host=ursim.host)
        return _Prepared(TransportSpec(run_id, sc.name, seed, str(setup), str(_plan(sc)), str(logs),
                                       ursim_host=ursim.host), ursim.stop)
    tracker = start_trackersim(run_dir, seed=seed, protocol=sc.protocol)
    setup = write_setup(sc, run_dir, seed=seed, tracker_port=tracker.port)
    return _Prepared(TransportSpec(run_id, sc.name, seed, str(setup), str(_plan(sc)), str(logs),
                                   tracker_control=str(tracker.control_path)), tracker.stop)


def run_transport_campaign(
    scenarios: list[TransportScenario], seeds: list[int], *, out_dir: Path, keep_logs: bool = False,
    timeout_s: float = TRANSPORT_TIMEOUT_S, jobs: int = 1, progress: Progress | None = None,
) -> dict[str, Any]:
    """Run every scenario x seed, ``jobs`` at a time (each run with its own emulator: the UR
    emulator on its own loopback address, the tracker emulator on its own pty; real time, so
    more than one job on a small machine loads the runs - 1 is the default); write
    ``transport.json`` and ``transport.html`` in ``out_dir``; return the summary (the simulator
    tier's shape, :func:`hil.campaign.report.summarise`). Blocking: ~15-30 s per run."""
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    say = progress or (lambda _m: None)
    logs = out_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    results: list[dict[str, Any]] = []
    todo = [(sc, seed) for seed in seeds for sc in scenarios]
    for first in range(0, len(todo), jobs):
        batch: list[_Prepared] = []
        try:
            for sc, seed in todo[first:first + jobs]:
                try:
                    batch.append(_prepare(sc, seed, logs))
                except EmulatorError as exc:
                    run_id = f"{sc.name}_s{seed}"
                    say(f"{run_id}: FAIL emulator did not start ({exc})")
                    results.append(RunResult(run_id, sc.name, sc.kind.value, sc.state, seed, passed=False,
                                             outcome="crashed", reasons=[f"emulator: {exc}"]).to_dict())
            if batch:
                results += run_parallel([b.spec for b in batch], jobs=len(batch), timeout_s=timeout_s,
                                        work_dir=logs, progress=say, run=run_transport_one)
        finally:
            for b in batch:
                b.stop()
        say(f"transport: {len(results)}/{len(todo)} runs done, "
            f"{sum(1 for r in results if not r.get('passed'))} failed")
    summary = summarise(results, config="(transport tier)")
    summary["tier"] = "transport"
    for f in summary["failing"]:
        f["replay"] = f"hil campaign --transport {f['scenario']} --seed {f['seed']}"
    if not keep_logs:
        _drop_passing_logs(logs, {f"{r['run_id']}" for r in results if not r.get("passed")})
    (out_dir / "transport.json").write_text(json.dumps(summary, indent=1, default=str) + "\n")
    (out_dir / "transport.html").write_text(render_html(summary, row_of=family_of, order=FAMILIES,
                                                        title="Transport fault campaign"))
    return summary


def _drop_passing_logs(logs: Path, failing: set[str]) -> None:
    """Delete the logs and run directories of passing runs (and ``logs`` when it ends empty)."""
    for p in sorted(logs.iterdir()):
        stem = p.name.removesuffix(".jsonl").removesuffix(".jsonl.head")
        if stem in failing:
            continue
        if p.is_dir():
            for q in p.iterdir():
                q.unlink()
            p.rmdir()
        else:
            p.unlink()
    if not any(logs.iterdir()):
        logs.rmdir()


def transport_table(results: list[dict[str, Any]]) -> str:
    """Fault family x state: ``pass`` / ``FAIL k/n`` and the worst safe-state latency (``-`` where
    the matrix has no run), then a line with the latency bounds per device."""
    text = table(results, row_of=family_of, order=FAMILIES)
    bounds: dict[str, float] = {}
    for r in results:
        b = r.get("latency_bound_ms")
        if isinstance(b, int | float) and r.get("kind"):
            bounds.setdefault(FAULT_DEVICE[FaultKind(r["kind"])], float(b))
    if bounds:
        text += "bounds: " + ", ".join(f"{d} {b:.0f} ms" for d, b in sorted(bounds.items())) + "\n"
    return text


def _plan(sc: TransportScenario) -> Path:
    return CONFIGS_DIR / "plans" / f"{Path(sc.base).stem}_plan.json"


