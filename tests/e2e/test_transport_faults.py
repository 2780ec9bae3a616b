"""The transport part of the fault layer without an emulator: the schedule's ``transport`` field,
the commands :class:`drivers.faults.TransportFaults` sends and when (ManualClock, polled), and the
refusals: no emulator fault channel, a simulated robot, a fault channel that is not on this
machine; and the UR driver's config carries nothing for the emulator."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

import configs
from drivers.faults import FaultyRobot, TransportFaults, transport_channel, wrap_device
from drivers.interfaces.errors import DisconnectedError, SafetyStopError
from drivers.interfaces.robot import MotionLimits, Robot, RobotState
from drivers.ur_rtde.config import UrRtdeRobotConfig
from drivers.ur_rtde.robot import UrRtdeRobot
from hil.campaign.ursim_control import UrsimControl
from hil.clock import ManualClock
from hil.config import build_devices, load_setup
from hil.config.faults import TRANSPORT_COMMANDS, FaultChannelConfig, FaultKind, FaultSpec
from hil.errors import ConfigError
from hil.geometry.transform import RigidTransform

CONFIGS = Path(configs.__file__).parent


class FakeChannel:
    """Records command lines; ``fail`` makes the next command raise like a dead fault channel."""

    def __init__(self, clock: ManualClock) -> None:
        self.clock = clock
        self.lines: list[tuple[float, str]] = []
        self.fail: Exception | None = None
        self.closed = 0

    def command(self, line: str) -> str:
        if self.fail is not None:
            exc, self.fail = self.fail, None
            raise exc
        self.lines.append((self.clock.now_ns() * 1e-9, line))
        return ""

    def close(self) -> None:
        self.closed += 1


def spec(kind: str, start_s: float, duration_s: float, **kw: Any) -> FaultSpec:
    return FaultSpec(kind=FaultKind(kind), start_s=start_s, duration_s=duration_s, **kw)


# ------------------------------------------------------------------ the schedule's shape
@pytest.mark.parametrize(("kind", "transport", "command"), [
    ("protective_stop", True, "protective_stop"),
    ("protective_stop", "estop", "estop"),
    ("robot_disconnect", True, "drop_connection"),
    ("motion_rejected", "stop_program", "stop_program"),
    ("motion_lag", True, "slow_responses"),
    ("motion_lag", "stall", "stall"),
    ("protective_stop", False, None),
])
def test_transport_command_of_a_fault(kind: str, transport: bool | str, command: str | None) -> None:
    assert spec(kind, 1.0, 1.0, transport=transport).transport_command == command


def test_every_robot_kind_has_transport_commands() -> None:
    robot_kinds = {k for k in FaultKind if spec(k.value, 0.0, 1.0).device == "robot"}
    assert set(TRANSPORT_COMMANDS) == robot_kinds


@pytest.mark.parametrize(("kind", "transport", "message"), [
    ("protective_stop", "stall", "does not cause a protective_stop"),
    ("motion_lag", "estop", "does not cause a motion_lag"),
    ("frame_drop", True, "do not apply to a frame_drop"),
    ("tracker_timeout", "estop", "do not apply to a tracker_timeout"),
    ("protective_stop", "reboot", "transport"),
])
def test_transport_refused_where_it_means_nothing(kind: str, transport: Any, message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        spec(kind, 1.0, 1.0, transport=transport)


# ------------------------------------------------------------------ what is sent, when
def play(faults: list[FaultSpec], until_s: float, step_s: float = 0.05) -> FakeChannel:
    clock = ManualClock()
    ch = FakeChannel(clock)
    tf = TransportFaults("robot", list(enumerate(faults)), ch, clock)
    t0 = clock.now_ns() * 1e-9
    tf.start(thread=False)
    while clock.now_ns() * 1e-9 - t0 < until_s:
        clock.advance(step_s)
        tf.poll()
    tf.stop()
    ch.lines = [(round(t - t0, 6), line) for t, line in ch.lines]
    return ch


def test_commands_at_window_start_and_end() -> None:
    ch = play([
        spec("protective_stop", 1.0, 0.5, transport=True),
        spec("protective_stop", 2.0, 1.0, transport="estop"),
        spec("robot_disconnect", 3.5, 1.5, transport=True),
        spec("motion_rejected", 5.5, 0.1, transport=True),
        spec("motion_lag", 6.0, 1.0, transport=True, lag_ms=250.0),
        spec("motion_lag", 7.5, 0.5, transport="stall"),
    ], until_s=9.0)
    assert ch.lines == [
        (1.0, "protective_stop"),
        (2.0, "estop"), (3.0, "release"),
        (3.5, "drop_connection 1.5"),
        (5.5, "stop_program"),
        (6.0, "slow_responses 250"), (7.0, "slow_responses 0"),
        (7.5, "stall on"), (8.0, "stall off"),
        (9.0, "release"),  # at stop(): the protective stop it caused is not left behind
    ]
    assert ch.closed == 1


def test_a_protective_stop_not_yet_started_is_not_released() -> None:
    ch = play([spec("protective_stop", 5.0, 1.0, transport=True)], until_s=1.0)
    assert ch.lines == []


def test_stop_closes_open_windows_and_skips_future_ones() -> None:
    ch = play([spec("motion_lag", 1.0, 10.0, transport="stall"),
               spec("protective_stop", 2.0, 5.0, transport="estop"),
               spec("protective_stop", 20.0, 1.0, transport=True)], until_s=3.0)
    assert ch.lines == [(1.0, "stall on"), (2.0, "estop"), (3.0, "release"), (3.0, "stall off")]


def test_a_failed_command_is_recorded_and_the_rest_still_sent() -> None:
    clock = ManualClock()
    ch = FakeChannel(clock)
    tf = TransportFaults("robot", [(0, spec("protective_stop", 1.0, 1.0, transport=True)),
                                   (1, spec("motion_rejected", 2.0, 1.0, transport=True))], ch, clock)
    tf.start(thread=False)
    ch.fail = DisconnectedError("ursim", "fault channel 127.0.0.1:30200 unreachable")
    clock.advance(1.0)
    assert tf.poll() is True
    clock.advance(1.0)
    assert tf.poll() is False
    assert tf.errors == ["protective_stop: ursim: fault channel 127.0.0.1:30200 unreachable"]
    assert [line for _, line in ch.lines] == ["stop_program"]


def test_the_thread_sends_on_its_own() -> None:
    clock = ManualClock()
    ch = FakeChannel(clock)
    tf = TransportFaults("robot", [(0, spec("robot_disconnect", 0.5, 2.0, transport=True))], ch, clock,
                         poll_s=0.001)
    tf.start()
    clock.advance(0.5)
    assert tf._thread is not None
    tf._thread.join(timeout=10.0)  # it ends once every command is sent
    assert not tf._thread.is_alive()
    assert [line for _, line in ch.lines] == ["drop_connection 2"]
    tf.stop()


# ------------------------------------------------------------------ the wrapper and the refusal
def ur_robot(**kw: Any) -> UrRtdeRobot:
    cfg = UrRtdeRobotConfig(driver="ur_rtde", host="127.0.0.1", **kw)
    return UrRtdeRobot("robot", MotionLimits(), cfg, ManualClock())


def test_channel_of_an_emulated_ur() -> None:
    ch = transport_channel(FaultChannelConfig(host="127.3.4.5", port=30201))
    assert isinstance(ch, UrsimControl)
    assert (ch.host, ch.port) == ("127.3.4.5", 30201)


def test_refused_without_a_fault_channel() -> None:
    with pytest.raises(ConfigError, match=r"no \[fault_channel\]"):
        wrap_device(ur_robot(), "robot", [spec("protective_stop", 1.0, 1.0, transport=True)], ManualClock())


def test_refused_for_a_simulated_robot(tmp_path: Path) -> None:
    setup = tmp_path / "sim.toml"
    setup.write_text((CONFIGS / "sim.toml").read_text().replace(
        'stereo = "calibration/sim_stereo.json"', f'stereo = "{CONFIGS / "calibration" / "sim_stereo.json"}"')
        + '\n[fault_channel]\nport = 30200\n\n[[faults]]\nkind = "protective_stop"\nstart_s = 1.0\n'
          'duration_s = 1.0\ntransport = true\n')
    with pytest.raises(ConfigError, match="robot driver 'sim' is simulated"):
        build_devices(load_setup(setup), ManualClock())


@pytest.mark.parametrize("host", ["192.0.2.10", "robot.lab", "10.0.0.1"])
def test_a_fault_channel_is_on_this_machine(host: str) -> None:
    with pytest.raises(ValidationError, match="not a loopback address"):
        FaultChannelConfig(host=host)
    assert FaultChannelConfig(host="localhost").port == 30200


def test_the_ur_driver_config_knows_no_emulator() -> None:
    with pytest.raises(ValidationError, match="emulator_control_port"):
        UrRtdeRobotConfig(driver="ur_rtde", host="127.0.0.1", emulator_control_port=30200)  # type: ignore[call-arg]


class StubRobot(Robot):
    """A robot that does nothing (the wrapper's own checks are under test)."""

    def __init__(self) -> None:
        super().__init__("robot", MotionLimits(), T_flange_from_tcp=RigidTransform.identity())
        self.recovered = 0

    @property
    def control_rate_hz(self) -> float:
        return 125.0

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _move_linear(self, T: RigidTransform, speed_mm_s: float, accel_mm_s2: float, blocking: bool) -> None:
        pass

    def _servo(self, T: RigidTransform, period_s: float) -> None:
        pass

    def _stop(self, decel_mm_s2: float) -> None:
        pass

    def _state_now(self) -> RobotState:
        raise NotImplementedError

    def recover(self) -> None:
        self.recovered += 1


def test_wrapper_splits_simulated_and_transport_faults() -> None:
    clock = ManualClock()
    ch = FakeChannel(clock)
    faults = [spec("protective_stop", 1.0, 2.0, transport=True), spec("motion_lag", 0.0, 1.0)]
    inner = StubRobot()
    robot = FaultyRobot(inner, faults, clock, channel=ch)
    assert robot.schedule.faults == (faults[1],)
    assert robot.transport is not None
    assert list(robot.transport.faults.values()) == [faults[0]]
    robot.open()
    clock.advance(1.5)
    robot.transport.poll()
    # inside the window recover() is refused before it reaches the driver, as for a simulated stop
    with pytest.raises(SafetyStopError, match="cannot be cleared yet"):
        robot.recover()
    assert inner.recovered == 0
    clock.advance(2.0)
    robot.recover()
    assert inner.recovered == 1
    robot.close()
    assert [line for _, line in ch.lines] == ["protective_stop", "release"]
    assert ch.closed == 1
