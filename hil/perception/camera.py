"""The camera as the supervisor sees it when perception runs in its own process, and the wiring
that puts it in a setup's devices (:func:`with_perception_process`)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from typing import Protocol, runtime_checkable

from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.lifecycle import Device
from hil.clock import Clock, MonotonicClock
from hil.config import Devices
from hil.config.setup import SetupConfig
from hil.errors import ConfigError
from hil.log import get_logger
from hil.perception.process import PerceptionProcess, PerceptionSpec
from hil.servo.client import ServoRobot
from hil.servo.process import ServoProcess
from hil.vision.camera_model import StereoCalibration

_log = get_logger(__name__)

#: structlog event: ``[perception] process = "auto"`` stays in-process, and why
EV_PERCEPTION_IN_PROCESS = "perception_in_process"

#: ``auto`` starts the perception process only with at least this many usable CPUs: one for the
#: servo loop, and one the supervisor and perception share. With one, every process would share
#: the loop's CPU. Three were asked until 2026-12-04: on two, perception then cost more than it
#: gained under the host's steal; with locating 4x cheaper since, it costs nothing measurable and
#: lowers the latency (docs/benchmarks.md, "Issue 16's figures on a quiet host").
AUTO_MIN_CPUS = 2


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask, not the machine's count)."""
    return len(os.sched_getaffinity(0))


class PerceptionCamera(StereoCamera):
    """The setup's camera, run by a :class:`PerceptionProcess` (module doc of
    :mod:`hil.perception.process`). ``open`` starts the process (the camera it builds is opened
    there; ``inner``, the one built here, is never opened), ``close`` ends it.

    :attr:`perception_feed` (the process) is the consumer the controller's pipeline takes marker
    sets from; :meth:`grab` takes the next one too and returns its stand-in pair (no images,
    timestamps as published: the rig's time offsets are applied in the perception process).
    """

    inner: StereoCamera

    def __init__(self, inner: StereoCamera, process: PerceptionProcess) -> None:
        super().__init__(inner.name)
        self.inner = inner
        self.process = process

    @property
    def perception_feed(self) -> PerceptionProcess:
        """The perception process: its located pairs are this camera's (never the inner
        camera's, which is never opened here)."""
        return self.process

    def _open(self) -> None:
        self.process.start()

    def _close(self) -> None:
        self.process.close()

    @property
    def calibration(self) -> StereoCalibration | None:
        return self.inner.calibration

    @property
    def frame_rate_hz(self) -> float:
        return self.inner.frame_rate_hz

    @property
    def exposure_us(self) -> float:
        return self.inner.exposure_us

    @property
    def image_size(self) -> tuple[int, int]:
        return self.inner.image_size

    def grab(self, timeout_s: float) -> StereoFrame:
        """The next published pair (see the class doc). Raises as :meth:`PerceptionProcess.take`."""
        self.require_active("grab")
        got = self.process.take(timeout_s)
        assert got is not None   # no wake: a pair or an error
        return got.frame


@dataclasses.dataclass
class PerceptionDevices(Devices):
    """Devices whose robot is opened first: the perception process is given the servo process's
    state ring, which exists once the robot (the servo process) is open."""

    def __iter__(self) -> Iterator[Device]:
        yield self.robot
        yield self.camera
        if self.tracker is not None:
            yield self.tracker


@runtime_checkable
class _World(Protocol):
    t0_ns: int
    breath_hold_listeners: list[object]


def _servo_process(robot: object) -> ServoProcess | None:
    """The servo process that owns ``robot`` (None: the servo loop runs in the supervisor)."""
    return robot.link if isinstance(robot, ServoRobot) and isinstance(robot.link, ServoProcess) else None


def in_supervisor_because(setup: SetupConfig, devices: Devices, clock: Clock) -> str | None:
    """Why perception stays in the supervisor's process for this setup, these devices and this
    clock (one line), or None when ``[perception] process`` starts the perception process (the
    rules: :func:`with_perception_process`). Never raises."""
    mode = setup.perception.process
    if mode == "off":
        return '[perception] process = "off"'
    world = devices.world
    if not isinstance(clock, MonotonicClock):
        return "it needs the wall clock ([simulation] real_time = true)"
    if setup.procedure.lock.needle_check is not None:
        return "the needle check ([procedure.lock.needle_check]) needs the images in the supervisor"
    if world is not None and _servo_process(devices.robot) is None:
        return "a simulated world needs the servo loop in its own process ([servo] process)"
    if world is not None and not isinstance(world, _World):
        return f"the simulated world ({type(world).__name__}) cannot follow a perception process"
    if mode == "auto" and (cpus := usable_cpus()) < AUTO_MIN_CPUS:   # a preference: "on" runs anyway
        return (f"{cpus} usable CPU, fewer than {AUTO_MIN_CPUS}: perception would share the servo loop's "
                'CPU ("on" starts it anyway)')
    return None


def with_perception_process(setup: SetupConfig, devices: Devices, clock: Clock) -> Devices:
    """``devices`` (not opened) with the camera replaced by a :class:`PerceptionCamera` when
    ``[perception] process`` asks for it and the setup allows it, else unchanged. Call it after
    :func:`~hil.controller.assembly.with_servo_process`.

    ``auto`` runs it on the wall clock unless the setup needs the images in the supervisor (a
    ``[procedure.lock.needle_check]``), has a simulated world while the servo loop runs in the
    supervisor (the perception process's world could not see the arm), or the process may use
    fewer than :data:`AUTO_MIN_CPUS` CPUs (:func:`usable_cpus`); on the wall clock
    ``perception_in_process`` is logged with the reason (:func:`in_supervisor_because`). A
    simulated world relays its breath-holds to the process.

    Raises:
        ConfigError: ``on`` where ``auto`` would stay in-process (names the reason and the key).
    """
    mode = setup.perception.process
    why = in_supervisor_because(setup, devices, clock)
    if why is not None:
        if mode == "on":
            raise ConfigError("setup", [f'perception.process: "on" cannot be used: {why}; use "auto" '
                                        '(it then runs where it can) or "off"'])
        if mode == "auto" and isinstance(clock, MonotonicClock):
            _log.info(EV_PERCEPTION_IN_PROCESS, reason=why)
        return devices
    robot = devices.robot
    servo = _servo_process(robot)
    world = devices.world

    def spec() -> PerceptionSpec:
        T_tcp = robot.T_flange_from_tcp.as_matrix()   # the servo process's, once it runs
        ring = servo.regions.ring_region.name if servo is not None and servo.ready is not None else None
        return PerceptionSpec(setup, servo_ring=ring,
                              T_flange_from_tcp=tuple(tuple(float(x) for x in row) for row in T_tcp),
                              world_t0_ns=world.t0_ns if isinstance(world, _World) else None,
                              cpu=setup.perception.cpu)

    process = PerceptionProcess(spec, devices.camera.name)
    if isinstance(world, _World):
        world.breath_hold_listeners.append(process.relay_breath_hold)
        if servo is not None:   # a restarted loop records the arm in a new ring
            servo.restart_listeners.append(process.relay_servo_ring)
    camera = PerceptionCamera(devices.camera, process)
    return PerceptionDevices(camera=camera, robot=devices.robot, tracker=devices.tracker, world=world)
