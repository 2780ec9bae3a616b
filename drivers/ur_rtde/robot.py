"""UR3 / UR3e arm over RTDE with the ``ur-rtde`` library (control, receive and dashboard clients).

This module is the only place where the project's millimetres and rotation matrices meet UR's
metres and axis-angle poses ``[x, y, z, rx, ry, rz]``.

Design (facts in reference/ur-rtde.md):
- Moves are sent asynchronously and then watched here, so the driver can stop a move that runs
  too long, notice a protective/emergency stop at once, and keep kicking the RTDE watchdog.
- Every library call goes through one lock: the watchdog kicker thread and the caller never
  interleave on the control interface's registers.
- After a lost connection the 1.6.5 control interface reconnects by itself in an endless loop;
  the driver never calls its ``reconnect()``: ``recover()`` disconnects all three clients and
  builds new ones.
- The pybind constructors hold the GIL and cannot time out; the driver first probes the three TCP
  ports with a timeout so an absent controller fails fast with DisconnectedError.
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.errors import (
    DeviceFaultError,
    DeviceTimeoutError,
    DisconnectedError,
    ProtocolError,
    SafetyStopError,
)
from drivers.interfaces.robot import (
    UR_FOLLOWING_ERROR_DEG,
    UR_FOLLOWING_ERROR_DURATION_S,
    UR_FOLLOWING_ERROR_MM,
    FollowingModel,
    MotionLimits,
    Robot,
    RobotMode,
    RobotState,
    SafetyStatus,
)
from drivers.ur_rtde.config import UrRtdeRobotConfig
from drivers.ur_rtde.dashboard import UrDashboard, wait_until
from drivers.ur_rtde.packet import READ_TRIES, one_packet
from drivers.ur_rtde.stream_age import StreamAge
from drivers.ur_rtde.watchdog import WatchdogKicker, armed_watchdog_hz
from drivers.ur_rtde.wire import (
    DASHBOARD_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    RobotModeCode,
    RuntimeState,
    SafetyStatusBit,
    rate_family,
)
from hil.clock import Clock
from hil.geometry.transform import RigidTransform
from hil.log import get_logger

FloatArray = NDArray[np.float64]
T = TypeVar("T")
_log = get_logger(__name__)

_Bit = SafetyStatusBit

RECEIVE_VARIABLES = [
    "timestamp", "actual_q", "actual_TCP_pose", "actual_TCP_speed", "robot_mode", "safety_mode",
    "runtime_state", "robot_status_bits", "safety_status_bits",
]


# ---------------------------------------------------------------------- unit conversion (boundary)
def pose_to_ur(T_base_from_flange: RigidTransform) -> list[float]:
    """RigidTransform (mm) -> UR pose ``[x, y, z, rx, ry, rz]`` (m, axis-angle rad)."""
    t_m = T_base_from_flange.t / 1000.0
    rv = T_base_from_flange.as_rotvec()
    return [float(t_m[0]), float(t_m[1]), float(t_m[2]), float(rv[0]), float(rv[1]), float(rv[2])]


def pose_from_ur(pose: Sequence[float], what: str = "pose") -> RigidTransform:
    """UR pose ``[x, y, z, rx, ry, rz]`` (m, axis-angle) -> RigidTransform (mm).

    Raises:
        ProtocolError: not 6 finite numbers.
    """
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise ProtocolError("robot", f"{what} from the controller is not 6 finite numbers: {list(pose)!r}")
    return RigidTransform.from_rotvec(p[3:], p[:3] * 1000.0)


def safety_from_bits(bits: int) -> SafetyStatus:
    """Map RTDE safety_status_bits to the interface's SafetyStatus (e-stop wins over p-stop)."""
    if bits & (_Bit.EMERGENCY_STOPPED | _Bit.ROBOT_EMERGENCY_STOPPED | _Bit.SYSTEM_EMERGENCY_STOPPED):
        return SafetyStatus.EMERGENCY_STOP
    if bits & (_Bit.VIOLATION | _Bit.FAULT):
        return SafetyStatus.FAULT
    if bits & (_Bit.PROTECTIVE_STOPPED | _Bit.SAFEGUARD_STOPPED):
        return SafetyStatus.PROTECTIVE_STOP
    return SafetyStatus.NORMAL


def trapezoid_time_s(distance: float, speed: float, accel: float) -> float:
    """Duration of a rest-to-rest acceleration-limited move (same units throughout)."""
    if distance <= 0:
        return 0.0
    t_acc = speed / accel
    if accel * t_acc * t_acc >= distance:  # triangular
        return 2.0 * math.sqrt(distance / accel)
    return 2.0 * t_acc + (distance - accel * t_acc * t_acc) / speed


def _probe(host: str, port: int, timeout_s: float, device: str) -> None:
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise DisconnectedError(device, f"cannot reach {host}:{port}: {exc}") from exc


class UrRtdeRobot(Robot):
    """A UR arm over RTDE. See the module doc for the design; ``Robot`` for the checked API.

    Args:
        name: role name (errors, logs).
        limits: hard motion limits (checked by the base class).
        cfg: the validated config.
        clock: the controller's clock (state timestamps, sleeps while watching a move).
    """

    def __init__(self, name: str, limits: MotionLimits, cfg: UrRtdeRobotConfig, clock: Clock) -> None:
        super().__init__(name, limits, T_flange_from_tcp=cfg.T_flange_from_tcp.as_transform())
        self.cfg = cfg
        self.clock = clock
        self.T_tcp_from_flange = self.T_flange_from_tcp.inverse()
        self._io = threading.RLock()
        self._ctrl: Any = None
        self._rcv: Any = None
        self._dashboard = UrDashboard(name, cfg, clock, self._io)
        self._servoing = False
        self._last_servo_ns = 0
        self._stream_age = StreamAge()
        self._kicker = WatchdogKicker(f"{name}-rtde-watchdog", self._kick_watchdog)

    # ------------------------------------------------------------------ lifecycle
    @property
    def control_rate_hz(self) -> float:
        return self.cfg.rate_hz

    @property
    def following_model(self) -> FollowingModel:
        """A UR arm following servoL: a first-order lag of ``0.3 * lookahead + 1 / gain`` s (the
        fit used by tools/ursim, ~33 ms at UR's defaults 0.1 s / 300), the UR bounds of
        docs/safety.md ("Following error")."""
        c = self.cfg
        tau_s = 0.3 * c.servo_lookahead_time_s + 1.0 / c.servo_gain
        return FollowingModel(tau_s, UR_FOLLOWING_ERROR_MM, UR_FOLLOWING_ERROR_DEG,
                              UR_FOLLOWING_ERROR_DURATION_S,
                              f"UR {c.controller} servoL lookahead {c.servo_lookahead_time_s:g} s, "
                              f"gain {c.servo_gain:g}")

    def _open(self) -> None:
        self._connect()

    def _close(self) -> None:
        """Stop the arm and the control script (only over a live link: with a dead one the library
        would wait on stale state), then disconnect all clients."""
        self._kicker.stop()
        link_ok = self._link_ok()
        with self._io:
            if self._ctrl is not None and link_ok:
                with contextlib.suppress(RuntimeError):
                    if self._servoing:
                        self._ctrl.servoStop(self.limits.max_accel_mm_s2 / 1000.0)
                    self._ctrl.stopScript()
            self._teardown()
        _log.info("robot_closed", device=self.name)

    def _connect(self) -> None:
        cfg = self.cfg
        for port in (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT):
            _probe(cfg.host, port, cfg.connect_timeout_s, self.name)
        import rtde_control
        import rtde_receive

        with self._io:
            try:
                version = self._dashboard.connect()
                self._check_version(version)
                self._rcv = rtde_receive.RTDEReceiveInterface(cfg.host, cfg.rate_hz, RECEIVE_VARIABLES)
                self._ctrl = rtde_control.RTDEControlInterface(cfg.host, cfg.rate_hz)
            except RuntimeError as exc:  # the library's std::runtime_error / logic_error
                self._teardown()
                raise DisconnectedError(self.name, f"ur-rtde could not connect to {cfg.host}: {exc}") from exc
            except Exception:  # e.g. the version check: leave no half-open client behind
                self._teardown()
                raise
            self._servoing = False
            self._stream_age.reset()
            hz = self._watchdog_hz()
            if hz > 0 and not self._ctrl.setWatchdog(hz):
                self._teardown()
                raise DeviceFaultError(self.name, "the control script refused setWatchdog")
        hz = self._watchdog_hz()
        if hz > 0:
            self._kicker.start(hz)
        _log.info("robot_connected", device=self.name, host=cfg.host, controller=cfg.controller,
                  polyscope=version, rate_hz=cfg.rate_hz)

    def _check_version(self, version: str) -> None:
        try:
            major = int(version.strip().split(".")[0])
        except ValueError as exc:
            raise ProtocolError(self.name, f"unreadable PolyScope version {version!r}") from exc
        found = rate_family(major)
        if found != self.cfg.controller:
            raise ProtocolError(
                self.name,
                f"controller reports PolyScope {version} ({found}) but the config says "
                f"controller = {self.cfg.controller!r}")

    def _teardown(self) -> None:
        """Disconnect and drop all three clients (never the control interface's own reconnect)."""
        for attr in ("_ctrl", "_rcv"):
            client = getattr(self, attr)
            if client is not None:
                with contextlib.suppress(RuntimeError):
                    client.disconnect()
            setattr(self, attr, None)
        self._dashboard.disconnect()
        self._servoing = False

    # ------------------------------------------------------------------ the RTDE watchdog
    def _watchdog_hz(self) -> float:
        """The watchdog rate armed (:func:`~drivers.ur_rtde.watchdog.armed_watchdog_hz`)."""
        return armed_watchdog_hz(self.cfg.rtde_watchdog_min_hz, self.limits, self.name)

    def _kick_watchdog(self, period_s: float) -> None:
        """The kicker's call, every ``period_s``: kick unless the link is down (the library would
        start its own, broken, reconnect) or a servo command in the last period already fed it."""
        with self._io:
            ctrl, rcv = self._ctrl, self._rcv
            if ctrl is None or rcv is None or not (rcv.isConnected() and ctrl.isConnected()):
                return
            if self._servoing and self.clock.now_ns() - self._last_servo_ns < period_s * 1e9:
                return
            with contextlib.suppress(RuntimeError):
                ctrl.kickWatchdog()

    # ------------------------------------------------------------------ helpers
    def _call(self, what: str, fn: Callable[[], T]) -> T:
        """One library call under the lock; library exceptions become DisconnectedError.

        Refused on a dead link: a control-interface command there starts the library's own
        reconnect, which 1.6.5 gets wrong (reference/ur-rtde.md trap 2)."""
        with self._io:
            try:
                self._require_connected()
            except DisconnectedError as exc:
                raise DisconnectedError(self.name, f"{what}: {exc.message}") from None
            try:
                return fn()
            except RuntimeError as exc:
                raise DisconnectedError(self.name, f"{what}: {exc}") from exc

    def _require_connected(self) -> tuple[Any, Any]:
        """The receive and control interfaces, both connected; else DisconnectedError."""
        rcv, ctrl = self._rcv, self._ctrl
        if rcv is None or ctrl is None:
            raise DisconnectedError(self.name, "not connected (call recover())")
        if not rcv.isConnected():
            raise DisconnectedError(self.name, "RTDE state stream lost (call recover())")
        if not ctrl.isConnected():
            raise DisconnectedError(self.name, "RTDE control connection lost (call recover())")
        return rcv, ctrl

    def _safety_and_running(self, what: str) -> tuple[SafetyStatus, bool]:
        """The arm's safety status and whether the control script runs, read from one packet: a
        protective stop (which stops the script too) is never read as "safety normal, script
        stopped". State reads only (no command lock).

        Raises:
            DisconnectedError: from :meth:`_require_connected`.
            DeviceTimeoutError: no packet could be read whole in ``READ_TRIES`` tries (``what``
                names the operation).
        """
        rcv, _ = self._require_connected()
        got = one_packet(rcv.getTimestamp,
                         lambda: (int(rcv.getSafetyStatusBits()), int(rcv.getRuntimeState())))
        if got is None:
            raise DeviceTimeoutError(self.name, f"{what}: the state could not be read from one packet in "
                                                f"{READ_TRIES} tries (the reads are starved)")
        bits, runtime = got[1]
        return safety_from_bits(bits), runtime == RuntimeState.PLAYING

    def _refused(self, command: str) -> Exception:
        """Why the control interface returned False: safety stop, stopped program or lost link."""
        try:
            safety, running = self._safety_and_running(f"{command} refused by the controller")
        except DeviceTimeoutError as exc:
            return exc
        if safety is not SafetyStatus.NORMAL:
            return SafetyStopError(self.name, f"{command} aborted: arm is in {safety}")
        if not running:
            return DeviceFaultError(
                self.name, f"{command} refused: the control script is not running "
                           "(stopped on the controller or by the RTDE watchdog; recover())")
        return DeviceFaultError(self.name, f"{command} refused by the controller")

    def _flange_pose(self, T_robot_from_tcp: RigidTransform) -> list[float]:
        return pose_to_ur(T_robot_from_tcp @ self.T_tcp_from_flange)

    # ------------------------------------------------------------------ state
    def _state_now(self) -> RobotState:
        # No command lock here: state reads never wait behind a command (a kick or a servo call
        # can block for seconds inside the library when the controller goes silent).
        rcv, ctrl = self._require_connected()
        try:   # one packet: a protective stop is never read as "safety normal, script stopped"
            got = one_packet(rcv.getTimestamp, lambda: (
                rcv.getActualTCPPose(), rcv.getActualQ(), rcv.getActualTCPSpeed(),
                int(rcv.getSafetyStatusBits()), int(rcv.getRuntimeState()), int(rcv.getRobotMode())))
        except RuntimeError as exc:
            raise DisconnectedError(self.name, f"reading state: {exc}") from exc
        if got is None:
            raise DeviceTimeoutError(self.name, f"state stream: a new packet arrived during each of "
                                                f"{READ_TRIES} reads (the reads are starved)")
        ts, (pose, q_raw, speed, bits, runtime, robot_mode) = got
        q = np.asarray(q_raw, dtype=np.float64)
        async_running = False
        with contextlib.suppress(RuntimeError):
            async_running = bool(ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning())
        now = self.clock.now_ns()
        age_s = self._stream_age.observe(ts, now * 1e-9)
        if age_s > self.cfg.state_max_age_s:
            raise DeviceTimeoutError(
                self.name, f"controller timestamp stuck at {ts:.3f} s for {age_s:.2f} s")
        T = pose_from_ur(pose, "actual_TCP_pose") @ self.T_flange_from_tcp
        tcp_speed_mm_s = float(np.linalg.norm(np.asarray(speed[:3], dtype=np.float64))) * 1000.0
        safety = safety_from_bits(bits)
        stopped = runtime != RuntimeState.PLAYING or robot_mode != RobotModeCode.RUNNING
        if safety is not SafetyStatus.NORMAL or stopped:
            mode = RobotMode.STOPPED
        elif self._servoing and now - self._last_servo_ns < 0.2e9:
            mode = RobotMode.SERVOING
        elif async_running or tcp_speed_mm_s > 0.5:
            mode = RobotMode.MOVING
        else:
            mode = RobotMode.IDLE
        return RobotState(T_robot_from_tcp=T, q_rad=q, mode=mode, safety=safety, t_ns=now,
                          tcp_speed_mm_s=tcp_speed_mm_s, sample_t_ns=now - round(age_s * 1e9))

    # ------------------------------------------------------------------ motion
    def _move_linear(self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
                     blocking: bool) -> None:
        """moveL (sent async, then watched when ``blocking``): the flange goes to the pose for the TCP."""
        target = self._flange_pose(T_robot_from_tcp)
        ctrl = self._ctrl
        start = self._state_now().T_robot_from_tcp
        op0 = self._call("moveL", lambda: int(ctrl.getAsyncOperationProgressEx().operationId()))
        if self._servoing:
            self._call("servoStop", lambda: ctrl.servoStop(accel_mm_s2 / 1000.0))
            self._servoing = False
        ok = self._call("moveL", lambda: bool(ctrl.moveL(target, speed_mm_s / 1000.0,
                                                         accel_mm_s2 / 1000.0, True)))
        if not ok:
            raise self._refused("moveL")
        _log.debug("robot_move_linear", device=self.name, target_mm=np.round(T_robot_from_tcp.t, 3).tolist(),
                   speed_mm_s=speed_mm_s, blocking=blocking)
        if not blocking:
            return
        dist = float(np.linalg.norm(T_robot_from_tcp.t - start.t))
        angle = (start.inverse() @ T_robot_from_tcp).rotation_angle_rad()
        expected_s = max(trapezoid_time_s(dist, speed_mm_s, accel_mm_s2),
                         trapezoid_time_s(angle * 1000.0, speed_mm_s, accel_mm_s2))
        deadline_ns = self.clock.now_ns() + int((1.5 * expected_s + self.cfg.move_timeout_margin_s) * 1e9)
        poll_s = 1.0 / self.control_rate_hz
        while True:
            self._require_connected()  # state reads only: no command lock
            st = ctrl.getAsyncOperationProgressEx()
            done = int(st.operationId()) != op0 and not st.isAsyncOperationRunning()
            safety, running = self._safety_and_running("moveL")
            if safety is not SafetyStatus.NORMAL:
                _log.warning("robot_safety_stop_during_move", device=self.name, safety=str(safety))
                raise SafetyStopError(self.name, f"moveL interrupted: arm is in {safety}")
            if not running:
                raise DeviceFaultError(self.name, "moveL interrupted: the control script stopped")
            if done:
                self._wait_next_state()
                return
            if self.clock.now_ns() > deadline_ns:
                with contextlib.suppress(DisconnectedError):  # async: a stuck arm must not block us
                    self._call("stopL", lambda: ctrl.stopL(accel_mm_s2 / 1000.0, True))
                allowed_s = 1.5 * expected_s + self.cfg.move_timeout_margin_s
                raise DeviceTimeoutError(
                    self.name, f"moveL did not finish within {allowed_s:.1f} s (arm stalled?); stopped it")
            self.clock.sleep(poll_s)

    def _wait_next_state(self) -> None:
        """Wait for one more state package: the receive stream may trail the control stream by a
        package, and a caller reading the state after a blocking move must see the final pose."""
        self._require_connected()
        rcv = self._rcv
        ts0 = float(rcv.getTimestamp())
        deadline_ns = self.clock.now_ns() + int(max(0.5, 3.0 / self.control_rate_hz) * 1e9)
        while float(rcv.getTimestamp()) <= ts0:
            if self.clock.now_ns() > deadline_ns:
                raise DeviceTimeoutError(self.name, "no state package after the move finished")
            self.clock.sleep(0.5 / self.control_rate_hz)

    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        """servoL toward the pose; ``period_s`` is servoL's blocking time ``t`` (>= one RTDE period)."""
        target = self._flange_pose(T_robot_from_tcp)
        t_s = max(period_s, 1.0 / self.control_rate_hz)
        ctrl = self._ctrl
        cfg = self.cfg
        if not self._servoing and self._call(
                "async status", lambda: bool(ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning())):
            # the script's servo thread would fight a running async move: stop it first
            self._call("stopL", lambda: ctrl.stopL(self.limits.max_accel_mm_s2 / 1000.0, False))
        ok = self._call("servoL", lambda: bool(ctrl.servoL(
            target, 0.5, 0.5, t_s, cfg.servo_lookahead_time_s, cfg.servo_gain)))
        if not ok:
            self._servoing = False
            raise self._refused("servoL")
        self._servoing = True
        self._last_servo_ns = self.clock.now_ns()

    def _stop(self, decel_mm_s2: float) -> None:
        """servoStop (while servoing) or stopL, with ``decel_mm_s2``; blocks until the arm is at rest."""
        ctrl = self._ctrl
        a = max(decel_mm_s2, 1.0) / 1000.0
        if self._servoing:
            self._servoing = False
            self._call("servoStop", lambda: ctrl.servoStop(a))
        else:
            self._call("stopL", lambda: ctrl.stopL(a, False))
        _log.info("robot_stopped", device=self.name, decel_mm_s2=decel_mm_s2)

    # ------------------------------------------------------------------ recovery
    def recover(self) -> None:
        """Rebuild lost interfaces, power the arm, unlock a protective stop, restart the control script.

        Blocks up to a few times ``ready_timeout_s``.

        Raises:
            SafetyStopError: the emergency stop is still engaged (release it on the pendant first).
            DisconnectedError: the controller stays unreachable after ``reconnect_attempts``.
            DeviceTimeoutError: the arm did not power on / unlock / start the script in time.
        """
        self.require_active("recover")
        if not self._link_ok():
            self._reconnect()
        if safety_from_bits(self._rcv_bits()) is SafetyStatus.EMERGENCY_STOP:
            raise SafetyStopError(self.name, "emergency stop engaged: release it, then recover()")
        self._require_connected()
        rcv = self._rcv
        self._dashboard.power_on(lambda: int(rcv.getRobotMode()))
        if safety_from_bits(self._rcv_bits()) is SafetyStatus.PROTECTIVE_STOP:
            self._dashboard.unlock_protective_stop(
                lambda: safety_from_bits(self._rcv_bits()) is SafetyStatus.NORMAL)
        self._require_connected()
        if int(self._rcv.getRuntimeState()) != RuntimeState.PLAYING:
            self._restart_script()
        _log.info("robot_recovered", device=self.name)

    def _rcv_bits(self) -> int:
        self._require_connected()
        return int(self._rcv.getSafetyStatusBits())

    def _link_ok(self) -> bool:
        try:
            self._state_now()
        except (DisconnectedError, DeviceTimeoutError):
            return False
        return True

    def _reconnect(self) -> None:
        self._kicker.stop()
        last: Exception | None = None
        for attempt in range(1, self.cfg.reconnect_attempts + 1):
            with self._io:
                self._teardown()
            try:
                self._connect()
                _log.info("robot_reconnected", device=self.name, attempt=attempt)
                return
            except (DisconnectedError, DeviceFaultError, ProtocolError) as exc:
                last = exc
                _log.warning("robot_reconnect_failed", device=self.name, attempt=attempt, error=str(exc))
                self.clock.sleep(self.cfg.reconnect_backoff_s)
        raise DisconnectedError(self.name, f"reconnect failed after {self.cfg.reconnect_attempts} attempts: "
                                           f"{last}")

    def _restart_script(self) -> None:
        ctrl = self._ctrl
        ok = self._call("reuploadScript", lambda: bool(ctrl.reuploadScript()))
        if not ok:
            raise DeviceFaultError(self.name, "could not upload the control script")
        rcv = self._rcv
        # both RTDE streams must see the script running: the control interface refuses commands
        # (setWatchdog returns False) while its own stream still shows the stopped program, even
        # when the receive interface's already shows it PLAYING (a race a loaded machine exposes)
        wait_until(self.clock, self.name, self.cfg.ready_timeout_s, "control script running",
                   lambda: int(rcv.getRuntimeState()) == RuntimeState.PLAYING
                   and bool(ctrl.isProgramRunning()))
        hz = self._watchdog_hz()  # the rate the kicker is paced for, as at connect
        if hz > 0 and not self._call("setWatchdog", lambda: bool(ctrl.setWatchdog(hz))):
            raise DeviceFaultError(self.name, "the control script refused setWatchdog")
