"""The emulated UR controller: arm state, the program's lifecycle, safety, RTDE outputs.

No sockets here: the servers feed input registers, uploaded programs and dashboard commands in,
call :meth:`UrController.tick` at the controller rate and read :meth:`UrController.outputs`.
Units are UR's (metres, radians, seconds). The program itself (ur-rtde's ``rtde_control`` script,
modelled by its register handshake, or a URScript program) is run by the controller's
:class:`~emulators.ursim.script.ControlScript`.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from emulators.ursim.motion import Motion, MotionError, SpeedJ
from emulators.ursim.pose import fast_rotvec, matrix_to_pose
from emulators.ursim.registers import Registers
from emulators.ursim.script import ControlScript, Program, parse_program
from hil.geometry.transform import RigidTransform
from hil.kinematics.ur import ur_inverse, ur_joint_frames

FloatArray = NDArray[np.float64]

#: A TCP target farther than this from the base (m) is unreachable for every UR arm.
_FAR_M = 100.0

HOME_Q = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])

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
        self.registers = Registers()
        self.in_int = self.registers.in_int      # the same lists: the script reads and writes them
        self.in_dbl = self.registers.in_dbl
        self.out_int = self.registers.out_int
        self.out_dbl = self.registers.out_dbl
        self.runtime_state = RuntimeState.STOPPED
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.estop_engaged = False
        self.program: Program | None = None
        self.motion: Motion | None = None
        self.blocking = False           # the script's main loop waits for the current motion
        self.async_running = False      # a move_thread / stop_thread is active
        self.executing_cmd = False      # the command in the register ran (cleared when it is 0 again)
        self.stalled = False
        self.slow_responses_s = 0.0
        self.speed_scaling = 1.0
        self.watchdog_hz: float | None = None
        self.last_kick_s = 0.0
        self.events: deque[str] = deque(maxlen=50)
        self.last_error = ""
        self._outputs: dict[str, Any] = {}
        self._target_cache: tuple[FloatArray, tuple[float, ...]] | None = None
        self._script = ControlScript(self)  # runs the program: the ur-rtde handshake, URScript
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
        """Apply one input data package (any connection; registers are controller-wide).

        The speed slider moves only when the package has ``speed_slider_mask`` = 1 (RTDE guide);
        writing the program's command register kicks the RTDE input watchdog.
        """
        fraction = self.registers.apply(values)
        if fraction is not None:
            self.speed_scaling = fraction
        if self.program is not None and f"input_int_register_{self.program.reg_offset}" in values:
            self.last_kick_s = self.timestamp_s

    def load_program(self, text: str) -> None:
        """A program arrived on the script port (30003): it replaces the running one."""
        prog = parse_program(text)
        self.end_program("replaced")
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
        self.motion = None
        self._script.start()
        self.log(f"program_started name={self.program.name if self.program else '?'}")

    def end_program(self, why: str, decel: float = PROGRAM_STOP_DECEL_RAD_S2) -> None:
        """Stop the program (if one runs: a ``program_stopped`` event); the arm decelerates at ``decel``."""
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

    def fault(self, message: str) -> None:
        """The program faults (a runtime error): ``last_error``, a ``program_fault`` event, it stops."""
        self.last_error = message
        self.log(f"program_fault {message}")
        self.end_program("fault")

    # ------------------------------------------------------------------ dashboard / faults
    def dashboard_stop(self) -> None:
        self.end_program("dashboard_stop")

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
        self.end_program("emergency_stop", PROTECTIVE_STOP_DECEL_RAD_S2)
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
        self.end_program("power_off")
        self.robot_mode = RobotMode.POWER_OFF
        self.motion = None

    def brake_release(self) -> bool:
        if self.estop_engaged or self.robot_mode is RobotMode.POWER_OFF:
            return False
        self.robot_mode = RobotMode.RUNNING
        return True

    def stop_program(self) -> None:
        self.end_program("fault_injection")

    def home(self, q: FloatArray | None = None) -> None:
        """Put the arm at ``q`` (default HOME_Q) at rest, cancelling any motion (an emulator-only jump)."""
        self.q = (HOME_Q if q is None else np.asarray(q, dtype=np.float64)).copy()
        self.q_target = self.q.copy()
        self.qd = np.zeros(6)
        self.motion = None
        self.tcp = self.fk(self.q)
        self.tcp_twist = np.zeros(6)
        self._script.motion_finished()
        self._update_outputs()
        self.log("home")

    # ------------------------------------------------------------------ the tick
    def _program_step(self) -> None:
        """Run the playing program for one tick; a URScript program past its last statement finishes."""
        prog = self.program
        if self.runtime_state is not RuntimeState.PLAYING or prog is None:
            return
        if self._script.step(prog):
            self.runtime_state = RuntimeState.STOPPED
            self.log(f"program_finished name={prog.name}")

    def tick(self) -> None:
        """Advance the controller by one period (1 / frequency_hz)."""
        self.timestamp_s += self.dt_s
        if (self.watchdog_hz is not None and self.runtime_state is RuntimeState.PLAYING
                and self.timestamp_s - self.last_kick_s > 1.0 / self.watchdog_hz):
            self.log("rtde_watchdog_expired")
            self.end_program("rtde_input_watchdog")
        self._program_step()
        q_prev = self.q.copy()
        T_prev = self.tcp
        if self.motion is not None and not self.stalled and self.robot_mode is RobotMode.RUNNING:
            try:
                done = self.motion.step(self, self.dt_s * self.speed_scaling)
            except MotionError as exc:
                self.fault(str(exc))
                done = True
                self.motion = None
            if done:
                self.motion = None
                self._script.motion_finished()
        self.qd = (self.q - q_prev) / self.dt_s
        self.tcp = self.fk(self.q)
        v = (self.tcp[:3, 3] - T_prev[:3, 3]) / self.dt_s
        w = fast_rotvec(self.tcp[:3, :3] @ T_prev[:3, :3].T) / self.dt_s
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
        pose = matrix_to_pose(self.tcp)
        if self.motion is None:
            target_pose = pose
        elif self._target_cache is not None and np.array_equal(self._target_cache[0], self.q_target):
            target_pose = self._target_cache[1]
        else:
            target_pose = matrix_to_pose(self.fk(self.q_target))
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
        register = self.registers.output(name)
        if register is not None:
            return register
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
            "tcp_pose": [round(x, 9) for x in matrix_to_pose(self.tcp)],
            "last_error": self.last_error,
            "events": list(self.events)[-10:],
            "wall_time": time.time(),
        }
