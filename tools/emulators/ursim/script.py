"""The programs the emulated UR controller runs: an uploaded program, parsed, then run tick by tick.

Two kinds of program arrive on the script port (30003):

* ur-rtde's ``rtde_control`` script (``scripts/rtde_control.script`` of ur-rtde 1.6.5), modelled by
  its register protocol rather than run line by line. Register indices are relative to the
  script's int register offset. The client writes a command code to input_int_register_0, the
  async flag to input_int_register_1 and the arguments to the input double registers; the script
  answers on output_int_register_0 with 1 (ready) or 2 (done) and puts results in the output
  registers. Real-time commands (:data:`RT_CMDS`: servo*, speed*, ...) are processed every tick and
  answer ready. The others run once per command (until the client writes 0) and answer done: at
  once, or, for a synchronous move or stop, when the motion ends (the controller's ``blocking``
  flag; the script's main loop waits meanwhile). An asynchronous move or stop answers done at once
  and reports in the async progress register (output_int_register_2) until the motion ends.
  :data:`STOP_SCRIPT` ends the program.
* any other program: run statement by statement in the URScript subset of ``urscript.py`` (moves,
  stops, ``sleep``, output register writes); a statement waits for the previous motion to end.

:class:`ControlScript` keeps only the interpreter's own bookkeeping. It reads and writes the arm,
the registers and the handshake flags of the controller it belongs to, through :class:`ScriptHost`
(what it needs, and all it knows, of the controller: this module imports no controller), and leaves
the program's lifecycle (``runtime_state``: start, stop, fault) to it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Protocol

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
from emulators.ursim.pose import matrix_to_pose, pose_to_matrix
from emulators.ursim.urscript import ScriptSyntaxError, Statement, parse_program_body
from hil.errors import GeometryError

FloatArray = NDArray[np.float64]

#: Commands the control script treats as real time: processed every tick, then "ready".
RT_CMDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
#: The command that ends the control script.
STOP_SCRIPT = 255


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
    """The program of an upload. Never raises: a URScript syntax error is kept in ``parse_error``."""
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
                T = pose_to_matrix(target) if is_pose else None
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


class ScriptHost(Protocol):
    """What the program interpreter reads and writes of the controller that runs it (units: m, rad,
    s). :class:`~emulators.ursim.controller.UrController` is one."""

    program: Program | None
    motion: Motion | None
    q: FloatArray
    qd: FloatArray
    q_target: FloatArray
    tcp: FloatArray                # 4x4 T_base_from_tool (m)
    timestamp_s: float
    in_int: list[int]
    in_dbl: list[float]
    out_int: list[int]
    out_dbl: list[float]
    blocking: bool                 # the script's main loop waits for the current motion
    async_running: bool            # a move_thread / stop_thread is active
    executing_cmd: bool            # the command in the register ran (cleared when it is 0 again)
    stalled: bool
    slow_responses_s: float
    watchdog_hz: float | None
    last_kick_s: float

    def fk(self, q: FloatArray) -> FloatArray:
        """4x4 T_base_from_tool (m) of joint angles ``q`` (rad)."""
        ...

    def ik(self, T: FloatArray, q_near: FloatArray) -> FloatArray | None:
        """Joint solution nearest ``q_near`` for a 4x4 pose (m), or None (unreachable)."""
        ...

    def log(self, event: str) -> None:
        """Record an event (the status's ``events``)."""
        ...

    def end_program(self, why: str, decel: float = ...) -> None:
        """Stop the program; the arm decelerates at ``decel`` (rad/s^2)."""
        ...

    def fault(self, message: str) -> None:
        """The program faults (a runtime error) and stops."""
        ...

    def protective_stop(self, why: str = ...) -> None:
        """A protective stop (the script's ``protective_stop`` command)."""
        ...


class ControlScript:
    """Runs the controller's program, one tick at a time. Not thread-safe (as the controller).

    Args:
        ctl: the controller that owns this interpreter (a :class:`ScriptHost`). The interpreter
            sets its ``motion`` and ``q_target``, its output registers and its handshake state (``blocking``,
            ``async_running``, ``executing_cmd``, ``watchdog_hz``, ``last_kick_s``), and calls its
            ``end_program``, ``fault`` and ``protective_stop``.
    """

    def __init__(self, ctl: ScriptHost) -> None:
        self._ctl = ctl
        self._cmd_seen: tuple[int, float] | None = None  # (command, when first seen): slow responses
        self._async_wr_count = 0   # async progress register: writes so far (mod 128)
        self._async_op_id = 0      # async progress register: asynchronous operations started (mod 128)
        self._pc = 0               # URScript program: index of the next statement
        self._sleep_until_s = 0.0  # URScript program: a ``sleep`` lasts until this controller time

    # ------------------------------------------------------------------ driven by the controller
    def start(self) -> None:
        """The controller (re)starts its program: reset; the control script signals ready."""
        self._cmd_seen = None
        self._pc = 0
        self._sleep_until_s = 0.0
        prog = self._ctl.program
        if prog is not None and prog.is_rtde_control:
            self._async_progress(-1)
            self._out_i(0, 1)

    def motion_finished(self) -> None:
        """The motion ended or was cancelled: a blocking command is done, an asynchronous one is over."""
        ctl = self._ctl
        if ctl.blocking:
            ctl.blocking = False
            self._out_i(0, 2)
        self._kill_async_move()

    def step(self, prog: Program) -> bool:
        """Run the playing program ``prog`` (the controller's) for one tick.

        Returns:
            True when ``prog``, a URScript program, has run its last statement: it is finished.
        """
        if not prog.is_rtde_control:
            return self._custom_step(prog)
        self._command_step()
        return False

    # ------------------------------------------------------------------ the rtde_control script
    def _command_step(self) -> None:
        """One pass of the control script's main loop: answer the command in the command register."""
        ctl = self._ctl
        if ctl.blocking:  # main loop inside a synchronous movel/movej/stopl
            return
        cmd = self._in_i(0)
        if cmd != 0 and ctl.slow_responses_s > 0:
            if self._cmd_seen is None or self._cmd_seen[0] != cmd:
                self._cmd_seen = (cmd, ctl.timestamp_s)
            if ctl.timestamp_s - self._cmd_seen[1] < ctl.slow_responses_s:
                return
        if cmd in RT_CMDS:
            try:
                self._process_rt(cmd)
            except (MotionError, GeometryError) as exc:
                ctl.fault(str(exc))
                return
            self._out_i(0, 1)
        elif cmd == 0:
            ctl.executing_cmd = False
            self._cmd_seen = None
            self._out_i(0, 1)
        elif not ctl.executing_cmd:
            ctl.executing_cmd = True
            if cmd == STOP_SCRIPT:
                ctl.log("cmd stop_script")
                ctl.end_program("stop_script")
                return
            try:
                blocking = self._process(cmd)
            except (MotionError, GeometryError) as exc:
                ctl.fault(str(exc))
                return
            if blocking:
                ctl.blocking = True
            else:
                self._out_i(0, 2)

    def _kill_async_move(self) -> None:
        ctl = self._ctl
        if ctl.async_running:
            ctl.async_running = False
            self._async_progress(-1)

    def _process_rt(self, cmd: int) -> None:
        """Run a real-time command (servoj/servoL retarget, speedj/speedl update); others are ignored.

        Raises:
            MotionError: an argument register is not finite.
            GeometryError: a pose argument the geometry library rejects (a rotation vector overflows).
        """
        ctl = self._ctl
        if cmd in (24, 11):
            target = self._in_d(0, 6)
            lookahead, gain = float(self._in_d(9)[0]), float(self._in_d(10)[0])
            if cmd == 24:
                q = ctl.ik(pose_to_matrix(target), ctl.q)
                if q is None:
                    ctl.fault("servoL: no inverse kinematics solution")
                    return
            else:
                q = target
            ctl.q_target = q
            if isinstance(ctl.motion, Servo):
                ctl.motion.retarget(q, lookahead, gain)
            else:
                ctl.motion = Servo(q, lookahead, gain)
        elif cmd == 10:
            xd = self._in_d(0, 6)
            acc = float(self._in_d(6)[0])
            if isinstance(ctl.motion, SpeedL) and not ctl.motion.stop_at_zero:
                ctl.motion.twist_target, ctl.motion.accel = xd, acc
            else:
                ctl.motion = SpeedL(xd, acc)
        elif cmd == 9:
            qd = self._in_d(0, 6)
            acc = float(self._in_d(6)[0])
            if isinstance(ctl.motion, SpeedJ) and not ctl.motion.stop_at_zero:
                ctl.motion.qd_target, ctl.motion.accel = qd, acc
            else:
                ctl.motion = SpeedJ(qd, acc, ctl.qd.copy())
        # other real-time commands (force mode, torques, ...) are accepted and ignored

    def _start_move(self, motion: Motion, is_async: bool) -> bool:
        """Replace the current motion. Returns True when the command blocks until it ends."""
        self._kill_async_move()
        self._ctl.motion = motion
        if is_async:
            self._ctl.async_running = True
            self._async_progress(0)
            return False
        return True

    def _process(self, cmd: int) -> bool:
        """Run a non-real-time command. Returns True when it blocks until the motion ends.

        Raises:
            MotionError: the command cannot run (no inverse kinematics solution, a non-finite argument).
            GeometryError: a pose argument the geometry library rejects (a rotation vector overflows).
        """
        ctl = self._ctl
        ctl.log(f"cmd {cmd}")
        is_async = self._in_i(1) == 1
        if cmd in (1, 2, 3, 4):
            return self._start_move(self._move(cmd), is_async)
        if cmd == 45:
            moves = list(ctl.program.move_path) if ctl.program else []
            return self._start_move(PathMove(moves), is_async)
        if cmd in (33, 34, 15, 16, 42):
            return self._stop(cmd, is_async)
        self._process_immediate(cmd)
        return False

    def _move(self, cmd: int) -> Motion:
        """The motion of a move command (1 to 4: to joints, to a pose by joints, linear, linear to
        the pose of joints) from its argument registers (target, speed, acceleration)."""
        ctl = self._ctl
        target = self._in_d(0, 6)
        speed, acc = float(self._in_d(6)[0]), float(self._in_d(7)[0])
        if cmd == 1:
            return JointMove(target, speed, acc)
        if cmd == 2:
            q = ctl.ik(pose_to_matrix(target), ctl.q)
            if q is None:
                raise MotionError("moveJ_IK: no inverse kinematics solution")
            return JointMove(q, speed, acc)
        if cmd == 3:
            T = pose_to_matrix(target)
            if ctl.ik(T, ctl.q) is None:
                raise MotionError("movel: target has no inverse kinematics solution")
            return LinearMove(T, speed, acc)
        return LinearMove(ctl.fk(target), speed, acc)

    def _stop(self, cmd: int, is_async: bool) -> bool:
        """A stop command: decelerate to rest. Returns True when it blocks until the arm is at rest."""
        ctl = self._ctl
        decel = float(self._in_d(0)[0]) if cmd != 42 else 1.2
        self._kill_async_move()
        if ctl.stalled or float(np.max(np.abs(ctl.qd))) < 1e-12:
            ctl.motion = None  # already at rest (a stalled arm too): the stop is complete
            return False
        if cmd in (33, 16, 15, 42) and not isinstance(ctl.motion, SpeedJ):
            stop: Motion = SpeedL(np.zeros(6), max(decel, 1e-3), name="stopl", stop_at_zero=True)
        else:
            stop = SpeedJ(np.zeros(6), max(decel, 1e-3), ctl.qd.copy(), name="stopj", stop_at_zero=True)
        ctl.motion = stop
        if cmd in (33, 34) and is_async:
            ctl.async_running = True
            self._async_progress(0)
            return False
        return True

    def _process_immediate(self, cmd: int) -> None:
        """A command that completes at once: kinematics queries, the watchdog, a protective stop, ...
        (commands the model does not know are accepted and answered done)."""
        ctl = self._ctl
        if cmd in (46, 30):
            pose = self._in_d(0, 6)
            near = self._in_d(6, 6) if cmd == 30 else ctl.q
            q = ctl.ik(pose_to_matrix(pose), near)
            if q is None:
                raise MotionError("get_inverse_kin: no solution")
            self._out_d(0, q)
        elif cmd in (43, 44):
            q = self._in_d(0, 6) if cmd == 44 else ctl.q
            self._out_d(0, matrix_to_pose(ctl.fk(q)))
        elif cmd in (60, 61):
            ok = ctl.ik(pose_to_matrix(self._in_d(0, 6)), ctl.q) is not None
            self._out_i(1, 1 if ok else 0)
        elif cmd == 35:
            hz = float(self._in_d(0)[0])
            ctl.watchdog_hz = hz if hz > 0 else None
            ctl.last_kick_s = ctl.timestamp_s
            ctl.log(f"watchdog_set min_hz={hz}")
        elif cmd == 31:
            ctl.protective_stop("script")
        elif cmd in (36, 37):
            self._out_i(1, 1)
        elif cmd == 40:
            self._out_d(0, [0.0] * 6)
        elif cmd == 58:
            self._out_d(0, matrix_to_pose(ctl.tcp))

    # ------------------------------------------------------------------ URScript programs
    def _custom_step(self, prog: Program) -> bool:
        """Run statements until one waits (a motion, a sleep) or the program ends (returns True)."""
        ctl = self._ctl
        while True:
            if ctl.motion is not None or ctl.timestamp_s < self._sleep_until_s:
                return False
            if self._pc >= len(prog.statements):
                return True
            st = prog.statements[self._pc]
            self._pc += 1
            try:
                self._execute(st)
            except (MotionError, GeometryError) as exc:
                ctl.fault(f"{prog.name}: {exc}")
                return False

    def _execute(self, st: Statement) -> None:
        """Run one statement; an unsupported one is skipped (and reported in the events).

        Raises:
            MotionError: a move target has no inverse kinematics solution.
            GeometryError: a target the geometry library rejects (e.g. a rotation vector overflows).
        """
        ctl = self._ctl
        if st.op == "movel":
            T = pose_to_matrix(st.values) if st.is_pose else ctl.fk(np.array(st.values))
            if ctl.ik(T, ctl.q) is None:
                raise MotionError(f"movel: target has no inverse kinematics solution ({st.text})")
            d = st.kw
            ctl.motion = LinearMove(T, d("v", 0.25), d("a", 1.2))
        elif st.op == "movej":
            q: FloatArray | None = np.array(st.values)
            if st.is_pose:
                q = ctl.ik(pose_to_matrix(st.values), ctl.q)
                if q is None:
                    raise MotionError(f"movej: pose has no inverse kinematics solution ({st.text})")
            assert q is not None
            ctl.motion = JointMove(q, st.kw("v", 1.05), st.kw("a", 1.4))
        elif st.op in ("stopl", "stopj"):
            if ctl.motion is not None or float(np.max(np.abs(ctl.qd))) > 1e-12:
                a = max(st.values[0], 1e-3)
                ctl.motion = (SpeedL(np.zeros(6), a, name="stopl", stop_at_zero=True) if st.op == "stopl"
                              else SpeedJ(np.zeros(6), a, ctl.qd.copy(), name="stopj", stop_at_zero=True))
        elif st.op == "sleep":
            self._sleep_until_s = ctl.timestamp_s + st.values[0]
        elif st.op == "write_int":
            ctl.out_int[int(st.values[0])] = int(st.values[1])
        elif st.op == "write_float":
            ctl.out_dbl[int(st.values[0])] = float(st.values[1])
        elif st.text and not st.text.startswith(("def ", "end", "global ", "textmsg")):
            ctl.log(f"statement_skipped {st.text[:60]!r}")

    # ------------------------------------------------------------------ registers (program offset)
    def _out_i(self, idx: int, value: int) -> None:
        ctl = self._ctl
        off = ctl.program.reg_offset if ctl.program else 0
        ctl.out_int[idx + off] = int(value)

    def _out_d(self, idx: int, values: Any) -> None:
        ctl = self._ctl
        off = ctl.program.reg_offset if ctl.program else 0
        for i, v in enumerate(values):
            ctl.out_dbl[idx + off + i] = float(v)

    def _in_i(self, idx: int) -> int:
        ctl = self._ctl
        off = ctl.program.reg_offset if ctl.program else 0
        return ctl.in_int[idx + off]

    def _in_d(self, idx: int, n: int = 1) -> FloatArray:
        """Input double registers ``idx..idx+n-1`` of the program.

        Raises:
            MotionError: one is NaN or infinite (the script would hand it to a motion command;
                a real controller faults the program on such a value).
        """
        ctl = self._ctl
        off = ctl.program.reg_offset if ctl.program else 0
        values = np.array(ctl.in_dbl[idx + off: idx + off + n], dtype=np.float64)
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
