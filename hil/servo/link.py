"""How the supervisor reaches the servo loop: the shared regions plus a small command channel.

Two links with one contract (:class:`ServoLink`):

- :class:`InProcessLink`: the loop and the robot live in this process and the loop is stepped by
  the caller (a simulated run on the manual clock: deterministic). Commands call the robot
  directly.
- :class:`~hil.servo.process.ServoProcess`: the loop runs in its own real-time process that owns
  the robot driver; commands travel over a pipe and are answered.

Command channel (rare, not per period): ``recover``, ``close``. Errors come back as the driver's
own error class, device and message. Motion of every kind (moves, tracking, hold, stop) goes
through the setpoint block.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

from drivers.interfaces.robot import FollowingModel, MotionLimits, Robot
from hil.clock import Clock
from hil.geometry.transform import RigidTransform
from hil.servo.limiter import RateLimiter
from hil.servo.loop import ServoLoop
from hil.servo.shm import SETPOINT_WORDS as SETPOINT_WORDS
from hil.servo.shm import LoopStats, SetpointBlock, ShmRegion, StateRing, ring_words, stats_words

if TYPE_CHECKING:
    from hil.servo.process import ServoReady

#: Ring slots: 2 s of periods at 500 Hz.
RING_SLOTS = 1024

class Regions:
    """The three shared regions of one servo loop (setpoint block, state ring, statistics)."""

    def __init__(self, setpoint: ShmRegion, ring: ShmRegion, stats: ShmRegion) -> None:
        self.setpoint_region, self.ring_region, self.stats_region = setpoint, ring, stats
        self.block = SetpointBlock(setpoint)
        self.ring = StateRing(ring, RING_SLOTS)
        self.stats = LoopStats(stats)

    @classmethod
    def create(cls, shared: bool) -> Regions:
        make = ShmRegion.create if shared else ShmRegion.local
        return cls(make(SETPOINT_WORDS), make(ring_words(RING_SLOTS)), make(stats_words()))

    @classmethod
    def attach(cls, names: tuple[str, str, str]) -> Regions:
        return cls(ShmRegion.attach(names[0], SETPOINT_WORDS),
                   ShmRegion.attach(names[1], ring_words(RING_SLOTS)),
                   ShmRegion.attach(names[2], stats_words()))

    def names(self) -> tuple[str, str, str]:
        names = (self.setpoint_region.name, self.ring_region.name, self.stats_region.name)
        assert None not in names, "local regions have no names"
        return (str(names[0]), str(names[1]), str(names[2]))

    def close(self) -> None:
        for r in (self.setpoint_region, self.ring_region, self.stats_region):
            r.close()


class ServoLink(Protocol):
    """What :class:`~hil.servo.client.ServoRobot` needs of a loop (module doc)."""

    regions: Regions
    in_process: bool
    #: what the servo process reported once ready (its pid, the CPUs the supervisor was moved
    #: to, ...); None for the loop in this process, and before a process is ready
    ready: ServoReady | None

    @property
    def robot_name(self) -> str: ...

    @property
    def control_rate_hz(self) -> float: ...

    @property
    def T_flange_from_tcp(self) -> RigidTransform: ...

    @property
    def following_model(self) -> FollowingModel:
        """The following-error lag and bounds the loop supervises with ([safety] overrides
        applied)."""
        ...

    def request(self, command: str, *args: Any, timeout_s: float = 5.0) -> Any:
        """Run a channel command; returns its result. Raises the driver's error, or
        DeviceTimeoutError / DisconnectedError when the loop does not answer or is gone."""
        ...

    def take_events(self) -> list[tuple[str, dict[str, Any]]]:
        """The loop's events since the last call (never blocks)."""
        ...

    def gone(self) -> str | None:
        """None while the loop runs; else why it is gone (exit code, crash)."""
        ...

    def kick(self) -> None:
        """After a STOP was written: step the in-process loop now (the process loop needs none)."""
        ...

    def wait_period(self) -> float:
        """Let one servo period pass (in-process: the clock sleeps a period, then the loop is
        stepped; the process loop runs by itself: a 5 ms sleep). Returns the time waited, s (the
        clock's; in-process exactly one period)."""
        ...

    def close(self) -> None: ...


class InProcessLink:
    """The loop in this process, stepped by the caller (module doc).

    Args:
        robot: the ACTIVE robot (owned by the caller; not closed here).
        limits, clock, period_s, limiter: see :class:`~hil.servo.loop.ServoLoop`.
    """

    in_process = True
    #: no servo process (:class:`ServoLink`)
    ready: ServoReady | None = None

    def __init__(self, robot: Robot, limits: MotionLimits, clock: Clock, limiter: RateLimiter) -> None:
        self.robot, self.clock = robot, clock
        self.regions = Regions.create(shared=False)
        self._events: list[tuple[str, dict[str, Any]]] = []
        self.loop = ServoLoop(robot, limits, clock, self.regions.block, self.regions.ring, self.regions.stats,
                              period_s=1.0 / robot.control_rate_hz, limiter=limiter, report=self._report)

    @property
    def robot_name(self) -> str:
        return self.robot.name

    @property
    def control_rate_hz(self) -> float:
        return self.robot.control_rate_hz

    @property
    def T_flange_from_tcp(self) -> RigidTransform:
        return self.robot.T_flange_from_tcp

    @property
    def following_model(self) -> FollowingModel:
        return self.loop.following.model

    def _report(self, kind: str, fields: dict[str, Any]) -> None:
        """The loop's events, kept until :meth:`take_events` (the same thread: no lock)."""
        self._events.append((kind, fields))

    def step(self, now_ns: int) -> None:
        """One period of the loop at ``now_ns``."""
        self.loop.step(now_ns)

    def request(self, command: str, *args: Any, timeout_s: float = 5.0) -> Any:
        if command == "recover":
            self.robot.recover()
            return None
        if command == "state":
            return self.robot.state_now()
        raise ValueError(f"unknown servo command {command!r}")

    def take_events(self) -> list[tuple[str, dict[str, Any]]]:
        out, self._events = self._events, []
        return out

    def gone(self) -> str | None:
        return None

    def kick(self) -> None:
        self.loop.step(self.clock.now_ns())

    def wait_period(self) -> float:
        self.clock.sleep(self.loop.period_s)
        self.loop.step(self.clock.now_ns())
        return self.loop.period_s

    def close(self) -> None:
        self.regions.close()
