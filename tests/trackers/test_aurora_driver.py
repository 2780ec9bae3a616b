"""AuroraTracker through the real pyserial on a pty, against the byte-exact emulator."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from emulators.trackersim.poses import StaticPoses
from pydantic import ValidationError

from drivers.interfaces.errors import DeviceFaultError, DeviceTimeoutError, DriverError, ProtocolError
from drivers.interfaces.tracker import TrackerSample
from drivers.tracker_serial.aurora import AuroraTracker
from drivers.tracker_serial.config import AuroraConfig
from hil.geometry.transform import RigidTransform

from .conftest import AuroraFactory, wait_until


def _config(port: str, **kw: object) -> AuroraConfig:
    base: dict[str, object] = {"driver": "aurora", "port": port,
                               "sensors": {"needle": "0A", "reference": "0b"},
                               "break_as_nul": True, "reset_timeout_s": 2.0, "response_timeout_s": 0.5,
                               "timeout_s": 0.5, "poll_rate_hz": 100.0}
    base.update(kw)
    return AuroraConfig.model_validate(base)


class Recorder:
    def __init__(self) -> None:
        self.samples: list[TrackerSample] = []

    def __call__(self, s: TrackerSample) -> None:
        self.samples.append(s)

    def count(self, sensor: str) -> int:
        return sum(1 for s in self.samples if s.sensor == sensor)


def _truth(dev: object, handle: str) -> RigidTransform:
    T = dev.poses.pose(handle, 0.0)  # type: ignore[attr-defined]
    assert T is not None
    return T


def _assert_matches(s: TrackerSample, truth: RigidTransform, tol_mm: float) -> None:
    assert s.T_tracker_from_sensor is not None
    np.testing.assert_allclose(s.T_tracker_from_sensor.t, truth.t, atol=tol_mm)
    assert (s.T_tracker_from_sensor.inverse() @ truth).rotation_angle_rad() < 2e-4


@pytest.mark.parametrize(("reply_format", "tol_mm"), [("bx", 1e-3), ("tx", 0.006)])
def test_tracking_at_115200(aurora_emulator: AuroraFactory, reply_format: str, tol_mm: float) -> None:
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, reply_format=reply_format))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        assert dev.baud == 115200
        assert dev.link.host_baud() == 115200
        assert tracker.info["handles"] == "0A,0B"
        wait_until(lambda: rec.count("needle") >= 10, what="10 frames")
        latest = tracker.latest()
    wait_until(lambda: dev.baud == 9600 and not dev.tracking, what="TSTOP and COMM back to 9600 on close")
    _assert_matches(latest["needle"], _truth(dev, "0A"), tol_mm)
    _assert_matches(latest["reference"], _truth(dev, "0B"), tol_mm)
    assert latest["needle"].quality == pytest.approx(0.05)
    frames = [s.seq for s in rec.samples if s.sensor == "needle"]
    assert frames == sorted(set(frames))  # each device frame once, in order


@pytest.mark.parametrize("fault", ["bad_crc,p=0.3", "garbage,p=0.3", "truncate,p=0.3"])
def test_damaged_replies_are_skipped(aurora_emulator: AuroraFactory, fault: str) -> None:
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, response_timeout_s=0.1, timeout_s=5.0))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        dev.faults.inject(fault, dev.now_s())
        wait_until(lambda: rec.count("needle") >= 30, what="frames despite damage")
        wait_until(lambda: tracker.damaged_records > 0, what="a damaged reply")
    assert dev.faults.fired[fault.split(",")[0]] > 0
    for s in rec.samples:
        _assert_matches(s, _truth(dev, "0A" if s.sensor == "needle" else "0B"), 1e-3)


def test_missing_and_out_of_volume_tools(aurora_emulator: AuroraFactory) -> None:
    poses = StaticPoses({"0A": None, "0B": RigidTransform.from_translation([0.0, 0.0, -800.0]),
                         "0C": RigidTransform.from_translation([0.0, 240.0, -250.0])})
    dev = aurora_emulator(n_tools=3, poses=poses)
    tracker = AuroraTracker(_config(dev.link.path, sensors={"needle": "0A", "ref": "0B", "edge": "0C"}))
    with tracker:
        wait_until(lambda: len(tracker.latest()) == 3, what="all three tools")
        latest = tracker.latest()
    assert latest["needle"].missing
    assert latest["needle"].T_tracker_from_sensor is None
    assert "missing" in latest["needle"].flags
    assert latest["ref"].missing
    assert latest["ref"].flags == ("out_of_volume",)
    assert not latest["edge"].missing
    assert latest["edge"].flags == ("partially_out",)


def test_silence_is_a_typed_timeout(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, timeout_s=0.2, response_timeout_s=0.1))
    with tracker:
        wait_until(lambda: "needle" in tracker.latest(), what="first frame")
        dev.faults.inject("silence", dev.now_s())

        def timed_out() -> bool:
            try:
                tracker.latest()
            except DeviceTimeoutError:
                return True
            return False

        wait_until(timed_out, what="DeviceTimeoutError")
        dev.faults.clear()


def test_no_reset_reply_without_break_on_a_pty(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, break_as_nul=False, reset_timeout_s=0.3))
    with pytest.raises(DeviceTimeoutError, match="no RESET after a serial break"):
        tracker.open()


def test_wrong_baud_after_comm_is_a_protocol_error(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path))
    tracker_ok = AuroraTracker(_config(dev.link.path, baud_rate=57600))
    dev.faults.inject("wrong_baud,baud=57600")  # COMM is accepted but the device ends up at 57600
    # The reset and INIT at 9600 are garbled too: the device really runs at 57600.
    with pytest.raises((ProtocolError, DeviceTimeoutError)):
        tracker.open()
    dev.faults.clear()
    with tracker_ok:
        wait_until(lambda: "needle" in tracker_ok.latest(), what="frames at 57600")


def test_unconfigured_handle_is_a_device_fault(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator(n_tools=1)
    tracker = AuroraTracker(_config(dev.link.path))
    with pytest.raises(DeviceFaultError, match="port handle 0B is not enabled"):
        tracker.open()


def test_device_reset_mid_tracking_is_a_device_fault(aurora_emulator: AuroraFactory) -> None:
    """Without re-initialisation the refusal stays (reinit_after_s = None)."""
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, timeout_s=30.0, reinit_after_s=None))
    with tracker:
        wait_until(lambda: "needle" in tracker.latest(), what="first frame")
        with dev.lock:
            dev.reset()
            dev.baud = 115200  # power cycle seen at the same speed: not tracking any more

        def faulted() -> bool:
            try:
                tracker.latest()
            except DeviceFaultError:
                return True
            return False

        wait_until(faulted, what="DeviceFaultError")
        assert not dev.tracking


def _raises(tracker: AuroraTracker, error: type[Exception]) -> Callable[[], bool]:
    def check() -> bool:
        try:
            tracker.latest()
        except error:
            return True
        return False
    return check


def _fresh_pose(tracker: AuroraTracker, sensor: str, after_seq: int) -> Callable[[], bool]:
    def check() -> bool:
        try:
            s = tracker.latest().get(sensor)
        except DriverError:
            return False
        return s is not None and not s.missing and s.seq != after_seq
    return check


def test_device_reset_at_the_comm_rate_is_re_initialised(aurora_emulator: AuroraFactory) -> None:
    """The reset fault (RESET at 9600, tracking stopped) while the host is at 115200: the polls get
    no answer, latest() times out, the driver runs the start-up again and frames flow again."""
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, timeout_s=0.3, response_timeout_s=0.2, reinit_after_s=0.4))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        wait_until(lambda: rec.count("needle") >= 5, what="first frames")
        before = rec.samples[-1].seq
        dev.faults.inject("reset", dev.now_s())
        wait_until(_raises(tracker, DeviceTimeoutError), what="DeviceTimeoutError after the reset")
        wait_until(lambda: dev.tracking and dev.baud == 115200, what="the driver's start-up again")
        wait_until(_fresh_pose(tracker, "needle", before), what="frames after the reset")
        after = tracker.latest()
    assert dev.faults.fired["reset"] == 1
    assert after["needle"].seq < before  # the frame counter restarted with TSTART
    _assert_matches(after["needle"], _truth(dev, "0A"), 1e-3)


def test_device_reset_seen_at_the_same_rate_is_re_initialised(aurora_emulator: AuroraFactory) -> None:
    """A reset seen as ERROR0C (host and device both at 9600): DeviceFaultError, then tracking again."""
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, baud_rate=9600, timeout_s=30.0, reinit_after_s=0.3))
    with tracker:
        wait_until(lambda: "needle" in tracker.latest(), what="first frame")
        seq = tracker.latest()["needle"].seq
        with dev.lock:
            dev.reset()
        wait_until(lambda: dev.tracking, what="the driver's start-up again")
        wait_until(_fresh_pose(tracker, "needle", seq), what="frames after the reset")


def test_a_wrong_baud_after_comm_in_the_restart_is_retried(aurora_emulator: AuroraFactory) -> None:
    """The device resets, and the COMM of the driver's start-up leaves it at 57600 instead of
    115200: VER gets no valid reply, that attempt fails (the condition stays), the next one after
    reinit_after_s succeeds."""
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, timeout_s=0.3, response_timeout_s=0.2, reinit_after_s=0.4))
    failures: list[str] = []
    tracker.log = _Spy(tracker.log, failures)
    with tracker:
        wait_until(lambda: "needle" in tracker.latest(), what="first frame")
        seq = tracker.latest()["needle"].seq
        dev.faults.inject("comm_baud,baud=57600", dev.now_s())
        dev.faults.inject("reset", dev.now_s())
        wait_until(lambda: dev.faults.fired["comm_baud"] == 1, what="the COMM to the wrong rate")
        wait_until(_fresh_pose(tracker, "needle", seq), what="frames after the second start-up")
        assert dev.baud == 115200
    assert len(failures) == 1
    assert "no valid reply at 115200 baud after COMM" in failures[0]


class _Spy:
    """A logger stand-in that keeps the errors of ``tracker_reinit_failed`` and passes all on."""

    def __init__(self, log: Any, failures: list[str]) -> None:
        self._log, self._failures = log, failures

    def warning(self, event: str, **fields: Any) -> None:
        if event == "tracker_reinit_failed":
            self._failures.append(str(fields["error"]))
        self._log.warning(event, **fields)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._log, name)


def test_no_answer_without_re_initialisation_stays_a_timeout(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, timeout_s=0.2, response_timeout_s=0.1,
                                    reinit_after_s=None))
    with tracker:
        wait_until(lambda: "needle" in tracker.latest(), what="first frame")
        dev.faults.inject("reset", dev.now_s())
        wait_until(_raises(tracker, DeviceTimeoutError), what="DeviceTimeoutError")
        assert not dev.tracking  # nobody started it again


def test_wrong_baud_mid_tracking_times_out_then_recovers(aurora_emulator: AuroraFactory) -> None:
    """The device leaves the COMM rate (runs at 57600): the host's polls are framing errors to it,
    so no answer; once it is back at the COMM rate, frames flow again."""
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, timeout_s=0.2, response_timeout_s=0.1, reinit_after_s=0.5))
    with tracker:
        wait_until(lambda: "needle" in tracker.latest(), what="first frame")
        seq = tracker.latest()["needle"].seq
        dev.faults.inject("wrong_baud,baud=57600", dev.now_s())
        wait_until(_raises(tracker, DeviceTimeoutError), what="DeviceTimeoutError")
        dev.faults.clear("wrong_baud")
        wait_until(_fresh_pose(tracker, "needle", seq), what="frames at the COMM rate again")


def test_bad_crc_on_every_reply_is_a_protocol_error_until_cleared(aurora_emulator: AuroraFactory) -> None:
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path, timeout_s=30.0, max_consecutive_damaged=5))
    with tracker:
        wait_until(lambda: "needle" in tracker.latest(), what="first frame")
        seq = tracker.latest()["needle"].seq
        dev.faults.inject("bad_crc,p=1", dev.now_s())
        wait_until(_raises(tracker, ProtocolError), what="ProtocolError")
        with pytest.raises(ProtocolError, match="5 damaged records in a row"):
            tracker.latest()
        dev.faults.clear("bad_crc")
        wait_until(_fresh_pose(tracker, "needle", seq), what="valid frames again")
        assert dev.tracking  # damaged replies never re-initialise a device that answers


@pytest.mark.parametrize(("fault", "flags"), [("tool_missing,handles=0B", ("missing",)),
                                              ("out_of_volume,handles=0B", ("out_of_volume",))])
def test_a_tool_going_missing_mid_tracking(aurora_emulator: AuroraFactory, fault: str,
                                           flags: tuple[str, ...]) -> None:
    """The reference (0B) missing or out of volume: a missing sample, no pose, the other tool still
    tracked, no error; the pose is back when the fault ends."""
    dev = aurora_emulator()
    tracker = AuroraTracker(_config(dev.link.path))
    with tracker:
        wait_until(lambda: "reference" in tracker.latest(), what="first frame")
        dev.faults.inject(fault, dev.now_s())
        wait_until(lambda: tracker.latest()["reference"].missing, what="reference missing")
        latest = tracker.latest()
        assert latest["reference"].T_tracker_from_sensor is None
        assert latest["reference"].flags == flags
        assert not latest["needle"].missing
        dev.faults.clear()
        wait_until(lambda: not tracker.latest()["reference"].missing, what="reference back")
        _assert_matches(tracker.latest()["reference"], _truth(dev, "0B"), 1e-3)


def test_frame_numbers_map_to_host_time_through_the_least_delayed_reply() -> None:
    tracker = AuroraTracker(_config("/dev/null", frame_rate_hz=40.0))
    # Frame 0 arrives 3 ms late, frame 1 only 1 ms late: the offset follows the least delay.
    assert tracker._frame_time_ns(0, 1_003_000_000) == 1_003_000_000
    assert tracker._frame_time_ns(1, 1_026_000_000) == 1_001_000_000 + 25_000_000
    assert tracker._frame_time_ns(2, 1_060_000_000) == 1_001_000_000 + 50_000_000


def test_config_handles() -> None:
    cfg = _config("/dev/x", sensors={"a": 10, "b": "0b"})
    assert cfg.sensors == {"a": "0A", "b": "0B"}
    with pytest.raises(ValueError, match="two hex digits"):
        _config("/dev/x", sensors={"a": "XYZ"})
    with pytest.raises(ValueError, match="share"):
        _config("/dev/x", sensors={"a": "0A", "b": 10})
    with pytest.raises(ValueError, match="COMM code"):
        _config("/dev/x", baud_rate=12345)


@pytest.mark.parametrize("value", [math.inf, math.nan])
def test_non_finite_timeouts_are_refused(value: float) -> None:
    """An infinite timeout_s would pass gt=0 and block forever: the config refuses it."""
    with pytest.raises(ValidationError, match="finite number"):
        _config("/dev/null", timeout_s=value)
