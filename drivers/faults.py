"""Fault injection: wrappers that play a fault schedule on any driver, real or simulated.

``wrap_device(device, role, faults, clock)`` returns a :class:`FaultyStereoCamera`,
:class:`FaultyRobot` or :class:`FaultyTracker` with the same interface as ``device``. Fault
windows are measured on the injected clock from the moment the wrapper was opened. Each fault
shows up at the interface as the typed error or flag a real failure would give, and logs
``fault_injected`` once when its window opens.

Robot faults with ``transport`` set are not simulated here: :class:`TransportFaults` sends them,
on a thread, at their scheduled times, to the fault channel of the UR controller emulator (the
setup's ``[fault_channel]``; its client is :class:`hil.campaign.ursim_control.UrsimControl`), and
the real driver meets them over the real protocol. The driver itself knows nothing of the
emulator. A setup without a fault channel (a real controller has none) refuses them with a
ConfigError when the wrapper is built.

The schedule's shape (:class:`hil.config.faults.FaultSpec`) belongs to the core; the wrappers
live here, outside it.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from drivers.interfaces.camera import Frame, PairFeed, StereoCamera, StereoFrame
from drivers.interfaces.errors import (
    DeviceFaultError,
    DeviceTimeoutError,
    DisconnectedError,
    DriverError,
    ProtocolError,
    SafetyStopError,
)
from drivers.interfaces.lifecycle import Device
from drivers.interfaces.robot import FollowingModel, Robot, RobotMode, RobotState, SafetyStatus
from drivers.interfaces.tracker import PoseTracker, TrackerSample
from hil.clock import Clock
from hil.config.faults import DEFAULT_FAULT_CHANNEL_PORT, FaultChannelConfig, FaultKind, FaultSpec
from hil.errors import ConfigError
from hil.geometry.transform import RigidTransform
from hil.log import get_logger
from hil.vision.camera_model import StereoCalibration

_log = get_logger(__name__)


def _rng(name: str, index: int) -> np.random.Generator:
    """Reproducible randomness of the fault layer (independent of any simulator)."""
    return np.random.default_rng([sum(name.encode()), index])


class _Schedule:
    """The faults of one device and when they are active (relative to open)."""

    def __init__(self, role: str, faults: Sequence[FaultSpec], clock: Clock) -> None:
        self.role = role
        self.faults = tuple(faults)
        self.clock = clock
        self.t_open_ns: int | None = None
        self._announced: set[int] = set()

    def start(self) -> None:
        self.t_open_ns = self.clock.now_ns()
        self._announced.clear()

    def t_s(self) -> float:
        return 0.0 if self.t_open_ns is None else (self.clock.now_ns() - self.t_open_ns) * 1e-9

    def active(self, kind: FaultKind) -> FaultSpec | None:
        """The first active fault of ``kind`` (logging ``fault_injected`` on its first use)."""
        if self.t_open_ns is None:
            return None
        t = self.t_s()
        for i, f in enumerate(self.faults):
            if f.kind is kind and f.active(t):
                if i not in self._announced:
                    self._announced.add(i)
                    _log.warning("fault_injected", device=self.role, kind=kind.value, index=i,
                                 start_s=f.start_s, duration_s=f.duration_s, t_s=round(t, 6))
                return f
        return None


class _Delegating:
    """Attributes the wrapper does not have (a simulator's extras such as ``world`` or
    ``last_truth``) come from ``inner``. What the core needs (a camera's ``calibration``, a
    robot's ``T_flange_from_tcp``) is part of the interface and delegated explicitly below."""

    def __getattr__(self, name: str) -> object:
        inner = self.__dict__.get("inner")
        if inner is None or name.startswith("__"):
            raise AttributeError(name)
        return getattr(inner, name)


class FaultyStereoCamera(_Delegating, StereoCamera):
    """A stereo camera with scheduled frame drops, frozen frames, stale timestamps, left/right
    desynchronisation, occlusions and glare blobs."""

    inner: StereoCamera

    def __init__(self, inner: StereoCamera, faults: Sequence[FaultSpec], clock: Clock) -> None:
        super().__init__(inner.name)
        self.inner = inner
        self.schedule = _Schedule(inner.name, faults, clock)
        self._last: StereoFrame | None = None
        self._prev_right: Frame | None = None
        self._drop_count = 0

    def _open(self) -> None:
        self.inner.open()
        self.schedule.start()

    def _close(self) -> None:
        self.inner.close()

    @property
    def frame_rate_hz(self) -> float:
        return self.inner.frame_rate_hz

    @property
    def exposure_us(self) -> float:
        return self.inner.exposure_us

    @property
    def image_size(self) -> tuple[int, int]:
        return self.inner.image_size

    @property
    def perception_feed(self) -> PairFeed[Any] | None:
        """The inner camera's (None for a camera the controller grabs), never one of its own."""
        return self.inner.perception_feed

    @property
    def calibration(self) -> StereoCalibration | None:
        """The inner camera's stereo calibration (None when it knows none), never a default."""
        return self.inner.calibration

    def grab(self, timeout_s: float) -> StereoFrame:
        self.require_active("grab")
        clock = self.schedule.clock
        deadline_ns = clock.now_ns() + round(timeout_s * 1e9)
        while True:
            remaining_s = (deadline_ns - clock.now_ns()) * 1e-9
            if remaining_s <= 0:
                raise DeviceTimeoutError(self.name, f"no stereo pair within {timeout_s} s")
            try:
                pair = self.inner.grab(remaining_s)
            except DeviceTimeoutError as exc:   # the whole wait, not what was left of it after drops
                raise DeviceTimeoutError(self.name, f"no stereo pair within {timeout_s} s") from exc
            drop = self.schedule.active(FaultKind.FRAME_DROP)
            if drop is None:
                break
            self._drop_count += 1
            if drop.probability < 1.0 and _rng("frame_drop", self._drop_count).random() >= drop.probability:
                break
        return self._apply(pair)

    def _apply(self, pair: StereoFrame) -> StereoFrame:
        s = self.schedule
        out = pair
        if s.active(FaultKind.FROZEN_FRAME) is not None and self._last is not None:
            out = StereoFrame(replace(pair.left, image=self._last.left.image),
                              replace(pair.right, image=self._last.right.image))
        else:
            self._last = pair
        if s.active(FaultKind.LR_DESYNC) is not None and self._prev_right is not None:
            out = StereoFrame(out.left, self._prev_right)
        self._prev_right = pair.right
        stale = s.active(FaultKind.STALE_TIMESTAMP)
        if stale is not None:
            age_ns = round(stale.age_ms * 1e6)
            out = StereoFrame(replace(out.left, t_ns=out.left.t_ns - age_ns),
                              replace(out.right, t_ns=out.right.t_ns - age_ns))
        occ = s.active(FaultKind.OCCLUSION)
        if occ is not None:
            out = StereoFrame(
                _occlude(out.left, occ) if occ.eye in ("left", "both") else out.left,
                _occlude(out.right, occ) if occ.eye in ("right", "both") else out.right)
        glare = s.active(FaultKind.GLARE)
        if glare is not None:
            out = _glare(out, glare, seq=pair.left.seq)
        return out


def _occlude(frame: Frame, f: FaultSpec) -> Frame:
    img = frame.image.copy()
    x0, y0, x1, y1 = f.region_px
    img[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = 200
    return replace(frame, image=img)


def _glare(pair: StereoFrame, f: FaultSpec, seq: int) -> StereoFrame:
    """Ring-shaped blobs (dark annulus, bright centre) at the same rows in both images, shifted by
    ``disparity_px``: the stereo matcher sees them as extra 3-D markers."""
    left, right = pair.left.image.copy(), pair.right.image.copy()
    h, w = left.shape[:2]
    rng = _rng("glare", seq)
    r = f.radius_px
    margin = int(r) + 2
    for _ in range(f.count):
        x = float(rng.uniform(margin + f.disparity_px, w - margin))
        y = float(rng.uniform(margin, h - margin))
        for img, cx in ((left, x), (right, x - f.disparity_px)):
            centre = (round(cx * 16), round(y * 16))
            cv2.circle(img, centre, round(r * 16), 40, -1, lineType=cv2.LINE_AA, shift=4)
            cv2.circle(img, centre, round(r * 0.43 * 16), 255, -1, lineType=cv2.LINE_AA, shift=4)
    return StereoFrame(replace(pair.left, image=left), replace(pair.right, image=right))


class FaultyTracker(_Delegating, PoseTracker):
    """A tracker with scheduled timeouts, corrupt records, bad-quality flags and missing sensors."""

    def __init__(self, inner: PoseTracker, faults: Sequence[FaultSpec], clock: Clock) -> None:
        super().__init__(inner.name)
        self.inner = inner
        self.schedule = _Schedule(inner.name, faults, clock)

    def _open(self) -> None:
        self.inner.open()
        self.schedule.start()

    def _close(self) -> None:
        self.inner.close()

    @property
    def sensors(self) -> tuple[str, ...]:
        return self.inner.sensors

    def latest(self) -> dict[str, TrackerSample]:
        self.require_active("latest")
        s = self.schedule
        if s.active(FaultKind.TRACKER_TIMEOUT) is not None:
            raise DeviceTimeoutError(self.name, "no valid record from the tracker (injected timeout)")
        if s.active(FaultKind.CORRUPT_RECORD) is not None:
            raise ProtocolError(self.name, "corrupt record: bad checksum (injected)")
        samples = self.inner.latest()
        bad = s.active(FaultKind.BAD_QUALITY)
        missing = s.active(FaultKind.SENSOR_MISSING)
        out = {}
        for name, smp in samples.items():
            if missing is not None and (not missing.sensors or name in missing.sensors):
                smp = replace(smp, T_tracker_from_sensor=None, missing=True, flags=(*smp.flags, "missing"))
            elif bad is not None and (not bad.sensors or name in bad.sensors):
                smp = replace(smp, quality=bad.quality, flags=(*smp.flags, "bad_quality"))
            out[name] = smp
        return out


@runtime_checkable
class LinkAware(Protocol):
    """A robot that models what the arm does when its command link drops (the simulator)."""

    def connection_lost(self, at_ns: int | None = None) -> None:
        """The link dropped at ``at_ns`` (default now): stop the running program / motion."""
        ...


class FaultyRobot(_Delegating, Robot):
    """A robot with scheduled disconnects, protective stops, rejected and lagging motion.

    The base class re-checks limits here, and the inner robot checks them again: faults never
    let a command skip the check.
    """

    def __init__(self, inner: Robot, faults: Sequence[FaultSpec], clock: Clock,
                 channel: FaultChannel | None = None,
                 fault_channel: FaultChannelConfig | None = None) -> None:
        super().__init__(inner.name, inner.limits, T_flange_from_tcp=inner.T_flange_from_tcp)
        self.inner = inner
        simulated = [f for f in faults if f.transport_command is None]
        sent = [(i, f) for i, f in enumerate(faults) if f.transport_command is not None]
        self.schedule = _Schedule(inner.name, simulated, clock)
        self.transport: TransportFaults | None = None
        if sent:
            self.transport = TransportFaults(
                inner.name, sent, channel if channel is not None else transport_channel(fault_channel), clock)
        self._stopped_by_fault = False
        self._link_down = False
        self._servo_queue: deque[tuple[int, RigidTransform, float]] = deque()

    def _open(self) -> None:
        self.inner.open()
        self.schedule.start()
        if self.transport is not None:
            self.transport.start()

    def _close(self) -> None:
        if self.transport is not None:
            self.transport.stop()
        self.inner.close()

    @property
    def control_rate_hz(self) -> float:
        return self.inner.control_rate_hz

    @property
    def following_model(self) -> FollowingModel:
        """The inner robot's."""
        return self.inner.following_model

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        """The inner robot's TCP in the flange frame (mm), never a default of its own."""
        return self.inner.T_flange_from_tcp

    def _check_connected(self) -> None:
        f = self.schedule.active(FaultKind.ROBOT_DISCONNECT)
        if f is None:
            self._link_down = False
            return
        if not self._link_down:
            self._link_down = True
            self._program_stops(f)
        raise DisconnectedError(self.name, "RTDE connection lost (injected)")

    def _program_stops(self, f: FaultSpec) -> None:
        """The link dropped: a UR's program stops, so the arm comes to rest during the outage. A
        robot that models it (:class:`LinkAware`, the simulator) stops from the onset; any other
        gets a stop now (when the drop is first noticed)."""
        assert self.schedule.t_open_ns is not None
        onset_ns = self.schedule.t_open_ns + round(f.start_s * 1e9)
        if isinstance(self.inner, LinkAware):
            self.inner.connection_lost(onset_ns)
        else:
            self.inner.stop()
        _log.warning("robot_link_lost_program_stopped", device=self.name, onset_ns=onset_ns)

    def _check_protective(self) -> None:
        if self.schedule.active(FaultKind.PROTECTIVE_STOP) is not None and not self._stopped_by_fault:
            self._stopped_by_fault = True
            self.inner.stop()

    def _state_now(self) -> RobotState:
        self._check_connected()
        self._check_protective()
        st = self.inner.state_now()
        if self._stopped_by_fault:
            st = replace(st, safety=SafetyStatus.PROTECTIVE_STOP, mode=RobotMode.STOPPED)
        return st

    def _check_motion(self) -> None:
        if self.schedule.active(FaultKind.MOTION_REJECTED) is not None:
            raise DeviceFaultError(self.name, "motion command rejected by the controller (injected)")

    def _move_linear(self, T_robot_from_tcp: RigidTransform, speed_mm_s: float, accel_mm_s2: float,
                     blocking: bool) -> None:
        self._check_connected()
        self._check_motion()
        lag = self.schedule.active(FaultKind.MOTION_LAG)
        if lag is not None:
            self.schedule.clock.sleep(lag.lag_ms * 1e-3)
        self.inner.move_linear(T_robot_from_tcp, speed_mm_s, accel_mm_s2, blocking=blocking)

    def _servo(self, T_robot_from_tcp: RigidTransform, period_s: float) -> None:
        self._check_connected()
        self._check_motion()
        lag = self.schedule.active(FaultKind.MOTION_LAG)
        now = self.schedule.clock.now_ns()
        if lag is None:
            # the window is over: the targets it still held back reach the arm now, in order and
            # late, then this one -- the stream never skips the held-back motion in one step (a
            # step of lag_ms of motion, which the arm's own step check refuses)
            self._deliver(now)
            self.inner.servo(T_robot_from_tcp, period_s)
            return
        self._servo_queue.append((now, T_robot_from_tcp, period_s))
        self._deliver(now - round(lag.lag_ms * 1e6))

    def _deliver(self, due_ns: int) -> None:
        """Hand the held-back servo targets commanded at or before ``due_ns`` to the arm, each in
        order (every step one period of the stream)."""
        while self._servo_queue and self._servo_queue[0][0] <= due_ns:
            _, T, period_s = self._servo_queue.popleft()
            self.inner.servo(T, period_s)

    def _stop(self, decel_mm_s2: float) -> None:
        self._check_connected()
        self._servo_queue.clear()
        self.inner.stop(decel_mm_s2)

    def recover(self) -> None:
        """Clears an injected protective stop once its window is over (and the inner one)."""
        self.require_active("recover")
        self._check_connected()
        if self.schedule.active(FaultKind.PROTECTIVE_STOP) is not None or (
                self.transport is not None and self.transport.active("protective_stop", "estop")):
            raise SafetyStopError(self.name, "protective stop cannot be cleared yet")
        self._stopped_by_fault = False
        self.inner.recover()


# ---------------------------------------------------------------------- faults through the transport
class FaultChannel(Protocol):
    """Where transport faults go: one emulator fault-channel command line per call
    (:class:`hil.campaign.ursim_control.UrsimControl`). Raises DriverError on failure."""

    def command(self, line: str) -> str: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class _Action:
    t_s: float
    index: int
    line: str
    phase: str  # "start" | "end" | "cleanup" (sent only by stop(), when the fault was started)


def _transport_actions(index: int, f: FaultSpec) -> list[_Action]:
    """The emulator commands of one transport fault (hil.config.faults.TRANSPORT_COMMANDS)."""
    cmd = f.transport_command
    start: dict[str | None, str] = {
        "protective_stop": "protective_stop", "estop": "estop",
        "drop_connection": f"drop_connection {f.duration_s:g}", "stop_program": "stop_program",
        "stall": "stall on", "slow_responses": f"slow_responses {f.lag_ms:g}",
    }
    end: dict[str | None, str] = {"estop": "release", "stall": "stall off",
                                  "slow_responses": "slow_responses 0"}
    out = [_Action(f.start_s, index, start[cmd], "start")]
    if cmd in end:
        out.append(_Action(f.end_s, index, end[cmd], "end"))
    if cmd == "protective_stop":  # the driver's recover() unlocks it; closing leaves none behind
        out.append(_Action(f.end_s, index, "release", "cleanup"))
    return out


class TransportFaults:
    """Plays transport faults on an emulator's fault channel at their scheduled times.

    A daemon thread, started by :meth:`start` (when the robot is opened), waits on the injected
    clock (polling every ``poll_s`` of wall time, so a ManualClock works too) and sends each
    command when its time comes, logging ``fault_injected`` (``transport=True``). :meth:`stop` ends
    the thread and sends the closing command (``release``, ``stall off``, ...) of every fault whose
    window was opened and not yet closed, and ``release`` for a protective stop it caused (a no-op
    when the driver already unlocked it), so the emulator is left as the run found it. A command the emulator
    rejects or cannot receive is logged (``transport_fault_failed``) and kept in :attr:`errors`.

    Args:
        role: device role (logs).
        faults: the transport faults (``transport_command`` not None), with their schedule index.
        channel: the emulator's fault channel.
        clock: the controller clock; times are relative to :meth:`start`.
    """

    def __init__(self, role: str, faults: Sequence[tuple[int, FaultSpec]], channel: FaultChannel,
                 clock: Clock, poll_s: float = 0.005) -> None:
        self.role = role
        self.faults = dict(faults)
        self.channel = channel
        self.clock = clock
        self.poll_s = poll_s
        every = [a for i, f in faults for a in _transport_actions(i, f)]
        self.actions = sorted((a for a in every if a.phase != "cleanup"),
                              key=lambda a: (a.t_s, a.phase != "end"))
        self.cleanup = [a for a in every if a.phase == "cleanup"]
        self.sent: list[tuple[float, str]] = []
        self.errors: list[str] = []
        self.t_open_ns: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._next = 0

    def t_s(self) -> float:
        return 0.0 if self.t_open_ns is None else (self.clock.now_ns() - self.t_open_ns) * 1e-9

    def start(self, thread: bool = True) -> None:
        """Time 0 is now; with ``thread`` (the default) a daemon thread calls :meth:`poll` every
        ``poll_s`` until every command is sent or :meth:`stop` is called."""
        self._join()
        self.t_open_ns = self.clock.now_ns()
        self._next = 0
        self._stop.clear()
        if thread:
            self._thread = threading.Thread(target=self._run, name=f"{self.role}-transport-faults",
                                            daemon=True)
            self._thread.start()

    def poll(self) -> bool:
        """Send every command that is due; False when none is left."""
        with self._lock:
            while self._next < len(self.actions) and self.t_s() >= self.actions[self._next].t_s:
                a = self.actions[self._next]
                self._next += 1
                self._send(a)
            return self._next < len(self.actions)

    def _run(self) -> None:
        while not self._stop.is_set() and self.poll():
            self._stop.wait(self.poll_s)

    def _send(self, a: _Action) -> None:
        f = self.faults[a.index]
        t = round(self.t_s(), 6)
        try:
            self.channel.command(a.line)
        except DriverError as exc:
            self.errors.append(f"{a.line}: {exc}")
            _log.error("transport_fault_failed", device=self.role, kind=f.kind.value, index=a.index,
                       command=a.line, error=str(exc), t_s=t)
            return
        self.sent.append((t, a.line))
        if a.phase == "start":
            _log.warning("fault_injected", device=self.role, kind=f.kind.value, index=a.index,
                         start_s=f.start_s, duration_s=f.duration_s, t_s=t, transport=True, command=a.line)
        else:
            _log.info("fault_window_closed", device=self.role, kind=f.kind.value, index=a.index,
                      t_s=t, transport=True, command=a.line, phase=a.phase)

    def active(self, *commands: str) -> bool:
        """A fault sent as one of ``commands`` is inside its window now."""
        t = self.t_s()
        return self.t_open_ns is not None and any(
            f.transport_command in commands and f.active(t) for f in self.faults.values())

    def _join(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None

    def stop(self) -> None:
        """End the thread; close the windows already opened (idempotent)."""
        self._join()
        with self._lock:
            started = {a.index for a in self.actions[:self._next] if a.phase == "start"}
            pending = [a for a in self.actions[self._next:] + self.cleanup
                       if a.phase != "start" and a.index in started]
            self._next = len(self.actions)
            for a in pending:
                self._send(a)
        self.channel.close()


def transport_channel(config: FaultChannelConfig | None) -> FaultChannel:
    """The client of the emulator fault channel ``config`` (the setup's ``[fault_channel]``), for
    transport faults. Connects on its first command.

    Raises:
        ConfigError: no fault channel configured (a real controller has none: transport faults
            cannot be injected there).
    """
    if config is None:
        raise ConfigError("setup", [
            "faults: transport faults need the UR emulator's fault channel, and the setup has no "
            "[fault_channel] (a real controller cannot be faulted through its transport); for "
            f"tools/ursim add [fault_channel] with host = the emulator's address, port = "
            f"{DEFAULT_FAULT_CHANNEL_PORT}"])
    from hil.campaign.ursim_control import UrsimControl

    return UrsimControl(config.host, config.port)


def wrap_device(device: Device, role: str, faults: Sequence[FaultSpec], clock: Clock,
                fault_channel: FaultChannelConfig | None = None) -> Device:
    """The fault wrapper registered by the built-in plugin; ``fault_channel`` is where transport
    faults go (the setup's ``[fault_channel]``).

    Raises:
        TypeError: ``device`` is not a camera, robot or tracker, or a fault does not fit its kind.
        ConfigError: transport faults without an emulator fault channel.
    """
    for f in faults:
        if f.device != role:
            raise TypeError(f"{f.kind.value} is a {f.device} fault, not for the {role}")
    if isinstance(device, StereoCamera):
        return FaultyStereoCamera(device, faults, clock)
    if isinstance(device, Robot):
        return FaultyRobot(device, faults, clock, fault_channel=fault_channel)
    if isinstance(device, PoseTracker):
        return FaultyTracker(device, faults, clock)
    raise TypeError(f"cannot inject faults into {type(device).__name__}")


__all__ = ["FaultChannel", "FaultyRobot", "FaultyStereoCamera", "FaultyTracker", "TransportFaults",
           "transport_channel", "wrap_device"]
