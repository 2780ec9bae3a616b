"""The emulated UR controller: arm state, the ``rtde_control`` script's command handshake, safety.

No sockets here: the servers feed input registers, uploaded programs and dashboard commands in,
call :meth:`UrController.tick` at the controller rate and read :meth:`UrController.outputs`.
Units are UR's (metres, radians, seconds). The handshake mirrors ``scripts/rtde_control.script`` of
ur-rtde 1.6.5: output_int_register_0 = 1 ready / 2 done, real-time commands (servo*, speed*) are
processed every tick and signal ready, other commands run once per command and signal done.
"""

from __future__ import annotations

import math
import re
import time
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from emulators.ursim.motion import (
    JointMove,
    LinearMove,
    Motion,
    MotionError,
    PathMove,
    Servo,
    SpeedJ,
    SpeedL,
)
from emulators.ursim.urscript import ScriptSyntaxError, Statement, parse_program_body
from hil.errors import GeometryError
from hil.geometry.transform import RigidTransform, matrix_to_rotvec, rotvec_to_matrix
from hil.kinematics.ur import ur_inverse, ur_joint_frames

FloatArray = NDArray[np.float64]

#: A TCP target farther than this from the base (m) is unreachable for every UR arm.
_FAR_M = 100.0

HOME_Q = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])

# Commands the control script treats as real time: processed every tick, then "ready".
RT_CMDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
STOP_SCRIPT = 255
PROTECTIVE_STOP_DECEL_RAD_S2 = 20.0
PROGRAM_STOP_DECEL_RAD_S2 = 5.0


class RuntimeState(IntEnum):
    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


class RobotMode(IntEnum):
    DISCONNECTED = 0
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    RUNNING = 7


class SafetyMode(IntEnum):
    NORMAL = 1
    PROTECTIVE_STOP = 3
    ROBOT_EMERGENCY_STOP = 7


JOINT_MODE_RUNNING = 253
JOINT_MODE_IDLE = 255
JOINT_MODE_POWER_OFF = 239


@dataclass(frozen=True)
class ControllerVersion:
    major: int
    minor: int
    bugfix: int
    build: int

    @classmethod
    def parse(cls, text: str) -> ControllerVersion:
        """``3.15`` -> 3.15.7.106331 (CB3), ``5.11`` -> 5.11.6.108663 (e-Series); 4 parts taken as given."""
        parts = [int(p) for p in text.split(".")]
        if len(parts) == 2:
            defaults = {3: (7, 106331), 5: (6, 108663)}
            bugfix, build = defaults.get(parts[0], (0, 0))
            parts += [bugfix, build]
        if len(parts) != 4:
            raise ValueError(f"controller version {text!r}: want MAJOR.MINOR or MAJOR.MINOR.BUGFIX.BUILD")
        return cls(*parts)

    @property
    def is_cb3(self) -> bool:
        return self.major <= 3

    @property
    def frequency_hz(self) -> float:
        return 125.0 if self.is_cb3 else 500.0

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.bugfix}.{self.build}"


@dataclass
class Program:
    """An uploaded program: ur-rtde's ``rtde_control`` script (modelled by its register handshake)
    or any other program, run statement by statement in the URScript subset of ``urscript.py``."""

    name: str
    text: str
    is_rtde_control: bool
    reg_offset: int = 0
    move_path: list[Motion] = field(default_factory=list)
    statements: list[Statement] = field(default_factory=list)
    parse_error: str = ""


_MOVE_LINE = re.compile(
    r"^\s*(movel|movej)\((p?)\[([^\]]*)\]\s*,\s*a=([-+0-9.eE]+)\s*,\s*v=([-+0-9.eE]+)", re.MULTILINE)


def parse_program(text: str) -> Program:
    m = re.match(r"\s*def\s+([A-Za-z_][A-Za-z0-9_]*)\s*\(", text)
    name = m.group(1) if m else "script"
    is_ctl = name == "rtde_control" and "rtde_cmd()" in text
    offset = 0
    mo = re.search(r"reg_offset_int = # int register offset\n(\d+)", text)
    if mo:
        offset = int(mo.group(1))
    moves: list[Motion] = []
    if "# inject move path\n" in text:
        seg = text.split("# inject move path\n", 1)[1]
        seg = seg.split("\n    end", 1)[0]
        for kind, is_pose, vals, a, v in _MOVE_LINE.findall(seg):
            target = np.array([float(x) for x in vals.split(",")])
            if kind == "movel":
                T = _pose_to_matrix(target) if is_pose else None
                if T is not None:
                    moves.append(LinearMove(T, float(v), float(a)))
            else:
                moves.append(JointMove(target, float(v), float(a)))
    statements: list[Statement] = []
    error = ""
    if not is_ctl:
        try:
            statements = parse_program_body(text)
        except ScriptSyntaxError as exc:
            error = str(exc)
    return Program(name, text, is_ctl, offset, moves, statements, error)


def _pose_to_matrix(pose: Any) -> FloatArray:
    p = np.asarray(pose, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(p[3:6])
    T[:3, 3] = p[:3]
    return T


def _fast_rotvec(R: FloatArray) -> FloatArray:
    """Rotation vector of a rotation matrix the controller made itself (no validation: hot path)."""
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = (float(R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0
    if c < -0.99:  # near pi the axis needs the symmetric part: use the validated path
        return matrix_to_rotvec(R)
    s2 = float(np.linalg.norm(v))  # 2 sin(angle)
    if s2 < 1e-300:
        return np.zeros(3)
    angle = math.atan2(s2 / 2.0, c)
    out: FloatArray = v * (angle / s2)
    return out


def _matrix_to_pose(T: FloatArray) -> tuple[float, ...]:
    rv = _fast_rotvec(T[:3, :3])
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), float(rv[0]), float(rv[1]), float(rv[2]))


class UrController:
    """The robot controller model. Not thread-safe: the server calls it from one event loop.

    Args:
        version: the reported controller version (3.x -> CB3 at 125 Hz, 5.x -> e-Series at 500 Hz).
        model: kinematics model (``ur3``; ``ur3e`` for e-Series arms).
        q_start: initial joint angles (rad).
    """

    def __init__(
        self, version: ControllerVersion, model: str = "ur3", q_start: FloatArray | None = None
    ) -> None:
        self.version = version
        self.model = model
        self.frequency_hz = version.frequency_hz
        self.dt_s = 1.0 / self.frequency_hz
        self.timestamp_s = 0.0
        self.q = (HOME_Q if q_start is None else np.asarray(q_start, dtype=np.float64)).copy()
        self.qd = np.zeros(6)
        self.q_target = self.q.copy()
        self.tcp = self.fk(self.q)
        self.tcp_twist = np.zeros(6)
        self.in_int = [0] * 48
        self.in_dbl = [0.0] * 48
        self.out_int = [0] * 48
        self.out_dbl = [0.0] * 48
        self.runtime_state = RuntimeState.STOPPED
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.estop_engaged = False
        self.program: Program | None = None
        self.motion: Motion | None = None
        self.blocking = False           # the script's main loop waits for the current motion
        self.async_running = False      # a move_thread / stop_thread is active
        self.executing_cmd = False
        self.stalled = False
        self.slow_responses_s = 0.0
        self.speed_scaling = 1.0
        self.watchdog_hz: float | None = None
        self.last_kick_s = 0.0
        self._cmd_seen: tuple[int, float] | None = None
        self._async_wr_count = 0
        self._async_op_id = 0
        self.events: deque[str] = deque(maxlen=50)
        self.last_error = ""
        self._outputs: dict[str, Any] = {}
        self._target_cache: tuple[FloatArray, tuple[float, ...]] | None = None
        self._pc = 0
        self._sleep_until_s = 0.0
        self._update_outputs()

    # ------------------------------------------------------------------ kinematics (m)
    def fk(self, q: FloatArray) -> FloatArray:
        T = ur_joint_frames(q, self.model)[-1].copy()   # (the frames are shared, read-only)
        T[:3, 3] /= 1000.0
        return T

    def ik(self, T: FloatArray, q_near: FloatArray) -> FloatArray | None:
        """Joint solution nearest ``q_near`` for the TCP pose ``T`` (m), or None (unreachable)."""
        if not np.all(np.abs(T[:3, 3]) < _FAR_M):  # also NaN; no float overflow in the mm scaling
            return None
        try:
            target = RigidTransform(T[:3, :3], T[:3, 3] * 1000.0)
        except ValueError:
            return None
        sols = ur_inverse(target, self.model, q_near=q_near)
        if sols.shape[0] == 0:
            return None
        return np.asarray(sols[0], dtype=np.float64)

    # ------------------------------------------------------------------ inputs
    def log(self, event: str) -> None:
        self.events.append(f"{self.timestamp_s:.3f} {event}")

    def set_inputs(self, values: dict[str, Any]) -> None:
        """Apply one input data package (any connection; registers are controller-wide)."""
        for name, value in values.items():
            if name.startswith("input_int_register_"):
                idx = int(name.rsplit("_", 1)[1])
                self.in_int[idx] = int(value)
                if self.program is not None and idx == self.program.reg_offset:
                    self.last_kick_s = self.timestamp_s
            elif name.startswith("input_double_register_"):
                self.in_dbl[int(name.rsplit("_", 1)[1])] = float(value)
            elif name == "speed_slider_fraction":
                self.speed_scaling = max(0.0, min(1.0, float(value)))

    def load_program(self, text: str) -> None:
        """A program arrived on the script port (30003): it replaces the running one."""
        prog = parse_program(text)
        self._end_program("replaced")
        if self.safety_mode is not SafetyMode.NORMAL or self.robot_mode is not RobotMode.RUNNING:
            self.log(f"program_refused name={prog.name} robot_mode={self.robot_mode.name} "
                     f"safety={self.safety_mode.name}")
            return
        self.program = prog
        if prog.parse_error:
            self.last_error = prog.parse_error
            self.log(f"program_refused name={prog.name} syntax: {prog.parse_error}")
            return
        self._start_program()

    def _start_program(self) -> None:
        self.runtime_state = RuntimeState.PLAYING
        self.executing_cmd = False
        self.blocking = False
        self.watchdog_hz = None
        self._cmd_seen = None
        self.motion = None
        self._pc = 0
        self._sleep_until_s = 0.0
        if self.program is not None and self.program.is_rtde_control:
            self._async_progress(-1)
            self._out_i(0, 1)
        self.log(f"program_started name={self.program.name if self.program else '?'}")

    def _end_program(self, why: str, decel: float = PROGRAM_STOP_DECEL_RAD_S2) -> None:
        if self.runtime_state in (RuntimeState.PLAYING, RuntimeState.PAUSED):
            self.log(f"program_stopped reason={why}")
        self.runtime_state = RuntimeState.STOPPED
        self.watchdog_hz = None
        self.blocking = False
        self.async_running = False
        self._stop_motion(decel)

    def _stop_motion(self, decel_rad_s2: float) -> None:
        if float(np.max(np.abs(self.qd))) > 1e-9:
            self.motion = SpeedJ(np.zeros(6), decel_rad_s2, self.qd.copy(), name="stop", stop_at_zero=True)
        else:
            self.motion = None

    # ------------------------------------------------------------------ dashboard / faults
    def dashboard_stop(self) -> None:
        self._end_program("dashboard_stop")

    def dashboard_play(self) -> bool:
        if self.program is None or self.program.parse_error:
            return False
        if self.safety_mode is not SafetyMode.NORMAL or self.robot_mode is not RobotMode.RUNNING:
            return False
        self._start_program()
        return True

    def dashboard_pause(self) -> None:
        if self.runtime_state is RuntimeState.PLAYING:
            self.runtime_state = RuntimeState.PAUSED
            self._stop_motion(PROGRAM_STOP_DECEL_RAD_S2)

    def protective_stop(self, why: str = "fault_injection") -> None:
        if self.safety_mode is SafetyMode.ROBOT_EMERGENCY_STOP:
            return
        self.safety_mode = SafetyMode.PROTECTIVE_STOP
        if self.runtime_state is RuntimeState.PLAYING:
            self.runtime_state = RuntimeState.PAUSED
        self.blocking = False
        self.async_running = False
        self._stop_motion(PROTECTIVE_STOP_DECEL_RAD_S2)
        self.log(f"protective_stop reason={why}")

    def unlock_protective_stop(self) -> bool:
        if self.safety_mode is not SafetyMode.PROTECTIVE_STOP:
            return self.safety_mode is SafetyMode.NORMAL
        self.safety_mode = SafetyMode.NORMAL
        self.log("protective_stop_released")
        return True

    def emergency_stop(self) -> None:
        self.estop_engaged = True
        self.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
        self._end_program("emergency_stop", PROTECTIVE_STOP_DECEL_RAD_S2)
        self.robot_mode = RobotMode.POWER_OFF  # brakes engage: the arm stops where it is
        self.motion = None
        self.log("emergency_stop")

    def release(self) -> None:
        """The operator releases the e-stop button / clears a protective stop's cause (fault channel)."""
        if self.estop_engaged:
            self.estop_engaged = False
            self.safety_mode = SafetyMode.NORMAL
            self.log("emergency_stop_released (robot stays powered off)")
        elif self.safety_mode is SafetyMode.PROTECTIVE_STOP:
            self.unlock_protective_stop()

    def power_on(self) -> bool:
        if self.estop_engaged:
            return False
        if self.robot_mode in (RobotMode.POWER_OFF, RobotMode.POWER_ON):
            self.robot_mode = RobotMode.IDLE
        return True

    def power_off(self) -> None:
        self._end_program("power_off")
        self.robot_mode = RobotMode.POWER_OFF
        self.motion = None

    def brake_release(self) -> bool:
        if self.estop_engaged or self.robot_mode is RobotMode.POWER_OFF:
            return False
        self.robot_mode = RobotMode.RUNNING
        return True

    def stop_program(self) -> None:
        self._end_program("fault_injection")

    def home(self, q: FloatArray | None = None) -> None:
        """Put the arm at ``q`` (default HOME_Q) at rest, cancelling any motion (an emulator-only jump)."""
        self.q = (HOME_Q if q is None else np.asarray(q, dtype=np.float64)).copy()
        self.q_target = self.q.copy()
        self.qd = np.zeros(6)
        self.motion = None
        self.tcp = self.fk(self.q)
        self.tcp_twist = np.zeros(6)
        if self.blocking:
            self.blocking = False
            self._out_i(0, 2)
        self._kill_async_move()
        self._update_outputs()
        self.log("home")

    # ------------------------------------------------------------------ registers
    def _out_i(self, idx: int, value: int) -> None:
        off = self.program.reg_offset if self.program else 0
        self.out_int[idx + off] = int(value)

    def _out_d(self, idx: int, values: Any) -> None:
        off = self.program.reg_offset if self.program else 0
        for i, v in enumerate(values):
            self.out_dbl[idx + off + i] = float(v)

    def _in_i(self, idx: int) -> int:
        off = self.program.reg_offset if self.program else 0
        return self.in_int[idx + off]

    def _in_d(self, idx: int, n: int = 1) -> FloatArray:
        """Input double registers ``idx..idx+n-1`` of the program.

        Raises:
            MotionError: one is NaN or infinite (the script would hand it to a motion command;
                a real controller faults the program on such a value).
        """
        off = self.program.reg_offset if self.program else 0
        values = np.array(self.in_dbl[idx + off: idx + off + n], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise MotionError(f"input_double_register_{idx + off + int(bad[0])} is not finite "
                              f"({values[bad[0]]})")
        return values

    def _async_progress(self, value: int) -> None:
        """write_async_progress_register of the control script (bit 15 running, bits 0-14 progress)."""
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        reg = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._out_i(2, reg)

    # ------------------------------------------------------------------ the control script
    def _script_step(self) -> None:
        if self.runtime_state is not RuntimeState.PLAYING or self.program is None:
            return
        if not self.program.is_rtde_control:
            self._custom_step(self.program)
            return
        if self.blocking:  # main loop inside a synchronous movel/movej/stopl
            return
        cmd = self._in_i(0)
        if cmd != 0 and self.slow_responses_s > 0:
            if self._cmd_seen is None or self._cmd_seen[0] != cmd:
                self._cmd_seen = (cmd, self.timestamp_s)
            if self.timestamp_s - self._cmd_seen[1] < self.slow_responses_s:
                return
        if cmd in RT_CMDS:
            try:
                self._process_rt(cmd)
            except (MotionError, GeometryError) as exc:
                self._fault(str(exc))
                return
            self._out_i(0, 1)
        elif cmd == 0:
            self.executing_cmd = False
            self._cmd_seen = None
            self._out_i(0, 1)
        elif not self.executing_cmd:
            self.executing_cmd = True
            if cmd == STOP_SCRIPT:
                self.log("cmd stop_script")
                self._end_program("stop_script")
                return
            try:
                blocking = self._process(cmd)
            except (MotionError, GeometryError) as exc:
                self._fault(str(exc))
                return
            if blocking:
                self.blocking = True
            else:
                self._out_i(0, 2)

    def _custom_step(self, prog: Program) -> None:
        """Run statements until one waits (a motion, a sleep) or the program ends."""
        while True:
            if self.motion is not None or self.timestamp_s < self._sleep_until_s:
                return
            if self._pc >= len(prog.statements):
                self.runtime_state = RuntimeState.STOPPED
                self.log(f"program_finished name={prog.name}")
                return
            st = prog.statements[self._pc]
            self._pc += 1
            try:
                self._execute(st)
            except (MotionError, GeometryError) as exc:
                self._fault(f"{prog.name}: {exc}")
                return

    def _execute(self, st: Statement) -> None:
        if st.op == "movel":
            T = _pose_to_matrix(st.values) if st.is_pose else self.fk(np.array(st.values))
            if self.ik(T, self.q) is None:
                raise MotionError(f"movel: target has no inverse kinematics solution ({st.text})")
            d = st.kw
            self.motion = LinearMove(T, d("v", 0.25), d("a", 1.2))
        elif st.op == "movej":
            q: FloatArray | None = np.array(st.values)
            if st.is_pose:
                q = self.ik(_pose_to_matrix(st.values), self.q)
                if q is None:
                    raise MotionError(f"movej: pose has no inverse kinematics solution ({st.text})")
            assert q is not None
            self.motion = JointMove(q, st.kw("v", 1.05), st.kw("a", 1.4))
        elif st.op in ("stopl", "stopj"):
            if self.motion is not None or float(np.max(np.abs(self.qd))) > 1e-12:
                a = max(st.values[0], 1e-3)
                self.motion = (SpeedL(np.zeros(6), a, name="stopl", stop_at_zero=True) if st.op == "stopl"
                               else SpeedJ(np.zeros(6), a, self.qd.copy(), name="stopj", stop_at_zero=True))
        elif st.op == "sleep":
            self._sleep_until_s = self.timestamp_s + st.values[0]
        elif st.op == "write_int":
            self.out_int[int(st.values[0])] = int(st.values[1])
        elif st.op == "write_float":
            self.out_dbl[int(st.values[0])] = float(st.values[1])
        elif st.text and not st.text.startswith(("def ", "end", "global ", "textmsg")):
            self.log(f"statement_skipped {st.text[:60]!r}")

    def _fault(self, message: str) -> None:
        self.last_error = message
        self.log(f"program_fault {message}")
        self._end_program("fault")

    def _kill_async_move(self) -> None:
        if self.async_running:
            self.async_running = False
            self._async_progress(-1)

    def _process_rt(self, cmd: int) -> None:
        if cmd in (24, 11):
            target = self._in_d(0, 6)
            lookahead, gain = float(self._in_d(9)[0]), float(self._in_d(10)[0])
            if cmd == 24:
                q = self.ik(_pose_to_matrix(target), self.q)
                if q is None:
                    self._fault("servoL: no inverse kinematics solution")
                    return
            else:
                q = target
            self.q_target = q
            if isinstance(self.motion, Servo):
                self.motion.retarget(q, lookahead, gain)
            else:
                self.motion = Servo(q, lookahead, gain)
        elif cmd == 10:
            xd = self._in_d(0, 6)
            acc = float(self._in_d(6)[0])
            if isinstance(self.motion, SpeedL) and not self.motion.stop_at_zero:
                self.motion.twist_target, self.motion.accel = xd, acc
            else:
                self.motion = SpeedL(xd, acc)
        elif cmd == 9:
            qd = self._in_d(0, 6)
            acc = float(self._in_d(6)[0])
            if isinstance(self.motion, SpeedJ) and not self.motion.stop_at_zero:
                self.motion.qd_target, self.motion.accel = qd, acc
            else:
                self.motion = SpeedJ(qd, acc, self.qd.copy())
        # other real-time commands (force mode, torques, ...) are accepted and ignored

    def _start_move(self, motion: Motion, is_async: bool) -> bool:
        self._kill_async_move()
        self.motion = motion
        if is_async:
            self.async_running = True
            self._async_progress(0)
            return False
        return True

    def _process(self, cmd: int) -> bool:
        """Run a non-real-time command. Returns True when it blocks until the motion ends."""
        self.log(f"cmd {cmd}")
        is_async = self._in_i(1) == 1
        if cmd in (1, 2, 3, 4):
            target = self._in_d(0, 6)
            speed, acc = float(self._in_d(6)[0]), float(self._in_d(7)[0])
            motion: Motion
            if cmd == 1:
                motion = JointMove(target, speed, acc)
            elif cmd == 2:
                q = self.ik(_pose_to_matrix(target), self.q)
                if q is None:
                    raise MotionError("moveJ_IK: no inverse kinematics solution")
                motion = JointMove(q, speed, acc)
            elif cmd == 3:
                T = _pose_to_matrix(target)
                if self.ik(T, self.q) is None:
                    raise MotionError("movel: target has no inverse kinematics solution")
                motion = LinearMove(T, speed, acc)
            else:
                motion = LinearMove(self.fk(target), speed, acc)
            return self._start_move(motion, is_async)
        if cmd == 45:
            moves = list(self.program.move_path) if self.program else []
            return self._start_move(PathMove(moves), is_async)
        if cmd in (33, 34, 15, 16, 42):
            decel = float(self._in_d(0)[0]) if cmd != 42 else 1.2
            self._kill_async_move()
            if self.stalled or float(np.max(np.abs(self.qd))) < 1e-12:
                self.motion = None  # already at rest (a stalled arm too): the stop is complete
                return False
            if cmd in (33, 16, 15, 42) and not isinstance(self.motion, SpeedJ):
                stop: Motion = SpeedL(np.zeros(6), max(decel, 1e-3), name="stopl", stop_at_zero=True)
            else:
                stop = SpeedJ(np.zeros(6), max(decel, 1e-3), self.qd.copy(), name="stopj", stop_at_zero=True)
            self.motion = stop
            if cmd in (33, 34) and is_async:
                self.async_running = True
                self._async_progress(0)
                return False
            return True
        if cmd in (46, 30):
            pose = self._in_d(0, 6)
            near = self._in_d(6, 6) if cmd == 30 else self.q
            q = self.ik(_pose_to_matrix(pose), near)
            if q is None:
                raise MotionError("get_inverse_kin: no solution")
            self._out_d(0, q)
        elif cmd in (43, 44):
            q = self._in_d(0, 6) if cmd == 44 else self.q
            self._out_d(0, _matrix_to_pose(self.fk(q)))
        elif cmd in (60, 61):
            ok = self.ik(_pose_to_matrix(self._in_d(0, 6)), self.q) is not None
            self._out_i(1, 1 if ok else 0)
        elif cmd == 35:
            hz = float(self._in_d(0)[0])
            self.watchdog_hz = hz if hz > 0 else None
            self.last_kick_s = self.timestamp_s
            self.log(f"watchdog_set min_hz={hz}")
        elif cmd == 31:
            self.protective_stop("script")
        elif cmd in (36, 37):
            self._out_i(1, 1)
        elif cmd == 40:
            self._out_d(0, [0.0] * 6)
        elif cmd == 58:
            self._out_d(0, _matrix_to_pose(self.tcp))
        return False

    # ------------------------------------------------------------------ the tick
    def tick(self) -> None:
        """Advance the controller by one period (1 / frequency_hz)."""
        self.timestamp_s += self.dt_s
        if (self.watchdog_hz is not None and self.runtime_state is RuntimeState.PLAYING
                and self.timestamp_s - self.last_kick_s > 1.0 / self.watchdog_hz):
            self.log("rtde_watchdog_expired")
            self._end_program("rtde_input_watchdog")
        self._script_step()
        q_prev = self.q.copy()
        T_prev = self.tcp
        if self.motion is not None and not self.stalled and self.robot_mode is RobotMode.RUNNING:
            try:
                done = self.motion.step(self, self.dt_s * self.speed_scaling)
            except MotionError as exc:
                self._fault(str(exc))
                done = True
                self.motion = None
            if done:
                self.motion = None
                if self.blocking:
                    self.blocking = False
                    self._out_i(0, 2)
                if self.async_running:
                    self.async_running = False
                    self._async_progress(-1)
        self.qd = (self.q - q_prev) / self.dt_s
        self.tcp = self.fk(self.q)
        v = (self.tcp[:3, 3] - T_prev[:3, 3]) / self.dt_s
        w = _fast_rotvec(self.tcp[:3, :3] @ T_prev[:3, :3].T) / self.dt_s
        self.tcp_twist = np.concatenate([v, w])
        if self.motion is None:
            self.q_target = self.q.copy()
        self._update_outputs()

    # ------------------------------------------------------------------ outputs
    def _safety_bits(self) -> int:
        if self.safety_mode is SafetyMode.PROTECTIVE_STOP:
            return (1 << 2) | (1 << 10)
        if self.safety_mode is SafetyMode.ROBOT_EMERGENCY_STOP:
            return (1 << 6) | (1 << 7) | (1 << 10)
        return 1

    def _update_outputs(self) -> None:
        pose = _matrix_to_pose(self.tcp)
        if self.motion is None:
            target_pose = pose
        elif self._target_cache is not None and np.array_equal(self._target_cache[0], self.q_target):
            target_pose = self._target_cache[1]
        else:
            target_pose = _matrix_to_pose(self.fk(self.q_target))
            self._target_cache = (self.q_target.copy(), target_pose)
        powered = self.robot_mode in (RobotMode.IDLE, RobotMode.RUNNING, RobotMode.POWER_ON)
        running = self.runtime_state is RuntimeState.PLAYING
        jm = (JOINT_MODE_RUNNING if self.robot_mode is RobotMode.RUNNING
              else JOINT_MODE_IDLE if powered else JOINT_MODE_POWER_OFF)
        q = tuple(float(x) for x in self.q)
        qd = tuple(float(x) for x in self.qd)
        zeros6 = (0.0,) * 6
        self._outputs = {
            "timestamp": self.timestamp_s,
            "target_q": tuple(float(x) for x in self.q_target), "target_qd": qd, "target_qdd": zeros6,
            "actual_q": q, "actual_qd": qd,
            "actual_TCP_pose": pose, "target_TCP_pose": target_pose,
            "actual_TCP_speed": tuple(float(x) for x in self.tcp_twist),
            "target_TCP_speed": tuple(float(x) for x in self.tcp_twist),
            "robot_mode": int(self.robot_mode), "safety_mode": int(self.safety_mode),
            "safety_status": int(self.safety_mode),
            "joint_mode": (jm,) * 6,
            "runtime_state": int(self.runtime_state),
            "robot_status_bits": (1 if powered else 0) | (2 if running else 0),
            "safety_status_bits": self._safety_bits(),
            "speed_scaling": self.speed_scaling, "target_speed_fraction": self.speed_scaling,
            "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0 if powered else 0.0,
            "joint_temperatures": (30.0,) * 6,
            "actual_execution_time": 0.2,
        }

    def output(self, name: str, rtde_type: str) -> Any:
        """The current value of an output variable (zeros for ones the model does not simulate)."""
        if name in self._outputs:
            return self._outputs[name]
        if name.startswith("output_int_register_"):
            return self.out_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self.out_dbl[int(name.rsplit("_", 1)[1])]
        if rtde_type == "VECTOR6D":
            return (0.0,) * 6
        if rtde_type == "VECTOR3D":
            return (0.0,) * 3
        if rtde_type == "VECTOR6INT32":
            return (0,) * 6
        if rtde_type == "DOUBLE":
            return 0.0
        return 0

    # ------------------------------------------------------------------ status
    def status(self) -> dict[str, Any]:
        return {
            "timestamp_s": round(self.timestamp_s, 6),
            "version": str(self.version),
            "frequency_hz": self.frequency_hz,
            "runtime_state": self.runtime_state.name,
            "robot_mode": self.robot_mode.name,
            "safety_mode": self.safety_mode.name,
            "estop_engaged": self.estop_engaged,
            "program": self.program.name if self.program else None,
            "motion": self.motion.name if self.motion else None,
            "stalled": self.stalled,
            "slow_responses_ms": round(self.slow_responses_s * 1000.0, 3),
            "watchdog_hz": self.watchdog_hz,
            "q_rad": [round(float(x), 9) for x in self.q],
            "tcp_pose": [round(x, 9) for x in _matrix_to_pose(self.tcp)],
            "last_error": self.last_error,
            "events": list(self.events)[-10:],
            "wall_time": time.time(),
        }
