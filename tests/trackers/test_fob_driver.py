"""FlockOfBirdsTracker through the real pyserial on a pty, against the byte-exact emulator."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces.errors import (
    DeviceTimeoutError,
    DisconnectedError,
    LifecycleError,
    ProtocolError,
)
from drivers.interfaces.tracker import TrackerSample
from drivers.tracker_serial.config import FlockOfBirdsConfig
from drivers.tracker_serial.fob import FlockOfBirdsTracker
from hil.geometry.transform import RigidTransform

from .conftest import FobFactory, wait_until

POS_TOL_MM = 0.12  # 14-bit words over 36": 4 x 914.4 / 32768 mm
ROT_TOL_RAD = math.radians(0.1)


def _config(port: str, **kw: object) -> FlockOfBirdsConfig:
    base: dict[str, object] = {"driver": "fob", "port": port, "sensors": {"stylus": 0}, "reset_hold_s": 0.0,
                               "reset_settle_s": 0.0, "auto_config_wait_s": 0.01, "timeout_s": 0.5,
                               "response_timeout_s": 0.5}
    base.update(kw)
    return FlockOfBirdsConfig.model_validate(base)


class Recorder:
    def __init__(self) -> None:
        self.samples: list[TrackerSample] = []

    def __call__(self, s: TrackerSample) -> None:
        self.samples.append(s)

    def count(self, sensor: str) -> int:
        return sum(1 for s in self.samples if s.sensor == sensor)


def _truth(dev: object, sensor_id: str) -> RigidTransform:
    T = dev.poses.pose(sensor_id, 0.0)  # type: ignore[attr-defined]
    assert T is not None
    return T


def _assert_matches(sample: TrackerSample, truth: RigidTransform) -> None:
    assert sample.T_tracker_from_sensor is not None
    np.testing.assert_allclose(sample.T_tracker_from_sensor.t, truth.t, atol=POS_TOL_MM)
    assert (sample.T_tracker_from_sensor.inverse() @ truth).rotation_angle_rad() < ROT_TOL_RAD


@pytest.mark.parametrize("record_format", ["position_angles", "position_matrix", "position_quaternion"])
def test_standalone_stream(fob_emulator: FobFactory, record_format: str) -> None:
    dev = fob_emulator()
    tracker = FlockOfBirdsTracker(_config(dev.link.path, record_format=record_format))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        assert tracker.info["model"] == "6DFOB"
        assert tracker.info["firmware"] == "3.67"
        wait_until(lambda: rec.count("stylus") >= 20, what="20 records")
        latest = tracker.latest()["stylus"]
    wait_until(lambda: dev.stream is False, what="STREAM STOP on close")
    _assert_matches(latest, _truth(dev, "0"))
    seqs = [s.seq for s in rec.samples]
    assert seqs == sorted(seqs)
    assert all(b >= a for a, b in zip([s.t_ns for s in rec.samples], [s.t_ns for s in rec.samples][1:],
                                      strict=False))


def test_flock_group_mode_addresses_birds(fob_emulator: FobFactory) -> None:
    dev = fob_emulator(n_birds=3)
    tracker = FlockOfBirdsTracker(_config(dev.link.path, sensors={"stylus": 1, "reference": 3}))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        wait_until(lambda: rec.count("stylus") >= 10 and rec.count("reference") >= 10, what="both birds")
        latest = tracker.latest()
        assert dev.group_mode
        assert dev.auto_configured
    _assert_matches(latest["stylus"], _truth(dev, "1"))
    _assert_matches(latest["reference"], _truth(dev, "3"))


def test_point_mode(fob_emulator: FobFactory) -> None:
    dev = fob_emulator(n_birds=2)
    tracker = FlockOfBirdsTracker(_config(dev.link.path, sensors={"a": 1, "b": 2}, mode="point",
                                          record_format="position_angles"))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        wait_until(lambda: rec.count("a") >= 5 and rec.count("b") >= 5, what="POINT replies")
        assert not dev.stream
    _assert_matches(rec.samples[-1], _truth(dev, "1" if rec.samples[-1].sensor == "a" else "2"))


@pytest.mark.parametrize("fault", ["garbage,p=0.3,mask=0x7f", "truncate,p=0.3", "lost_phase,p=0.3"])
def test_damage_skips_records_and_never_yields_a_corrupt_pose(fob_emulator: FobFactory, fault: str) -> None:
    dev = fob_emulator(n_birds=2)
    dev.faults.inject(fault)
    tracker = FlockOfBirdsTracker(_config(dev.link.path, sensors={"a": 1, "b": 2}, max_step_mm=None))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        wait_until(lambda: rec.count("a") >= 40, what="records despite damage")
        assert tracker.damaged_records > 0
        assert set(tracker.latest()) == {"a", "b"}
    kind = fault.split(",")[0]
    assert dev.faults.fired[kind] > 0
    for s in rec.samples:
        _assert_matches(s, _truth(dev, "1" if s.sensor == "a" else "2"))


def test_full_byte_garbage_is_survived_and_forged_jumps_are_gated(fob_emulator: FobFactory) -> None:
    dev = fob_emulator()
    dev.faults.inject("garbage,p=0.3,bytes=3")
    tracker = FlockOfBirdsTracker(_config(dev.link.path, max_step_mm=5.0))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        wait_until(lambda: rec.count("stylus") >= 40, what="records despite garbage")
        assert tracker.damaged_records > 0
    truth = _truth(dev, "0")
    # The Bird's records have no checksum; whatever passed framing, content and the step gate is
    # within the gate of the truth.
    for s in rec.samples:
        assert s.T_tracker_from_sensor is not None
        assert np.linalg.norm(s.T_tracker_from_sensor.t - truth.t) < 5.0 + POS_TOL_MM


def test_silence_is_a_typed_timeout_and_recovers(fob_emulator: FobFactory) -> None:
    dev = fob_emulator()
    tracker = FlockOfBirdsTracker(_config(dev.link.path, timeout_s=0.2))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        wait_until(lambda: rec.count("stylus") >= 3, what="first records")
        dev.faults.inject("silence", dev.now_s())

        def timed_out() -> bool:
            try:
                tracker.latest()
            except DeviceTimeoutError:
                return True
            return False

        wait_until(timed_out, what="DeviceTimeoutError")
        dev.faults.clear("silence")
        n = rec.count("stylus")
        wait_until(lambda: rec.count("stylus") > n + 2, what="records after the silence")
        assert "stylus" in tracker.latest()


def test_wrong_baud_fails_open_with_protocol_or_timeout_error(fob_emulator: FobFactory) -> None:
    dev = fob_emulator(baud=38400)  # the dip switches say 38400, the config says 115200
    tracker = FlockOfBirdsTracker(_config(dev.link.path))
    with pytest.raises((ProtocolError, DeviceTimeoutError), match=r"baud|bytes"):
        tracker.open()
    assert dev.error_code == 11  # the Bird saw framing errors


def test_matching_baud_works_at_other_rates(fob_emulator: FobFactory) -> None:
    dev = fob_emulator(baud=38400)
    tracker = FlockOfBirdsTracker(_config(dev.link.path, baud_rate=38400))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        wait_until(lambda: rec.count("stylus") >= 3, what="records at 38400")


def test_unrecoverable_garbage_is_a_protocol_error(fob_emulator: FobFactory) -> None:
    dev = fob_emulator()
    tracker = FlockOfBirdsTracker(_config(dev.link.path, max_consecutive_damaged=5, timeout_s=30.0))
    with tracker:
        wait_until(lambda: "stylus" in tracker.latest(), what="streaming")  # STREAM was understood
        dev.faults.inject("wrong_baud,baud=9600")  # the line turns to noise mid-stream

        def protocol_error() -> bool:
            try:
                tracker.latest()
            except ProtocolError:
                return True
            return False

        wait_until(protocol_error, what="ProtocolError")


def test_no_device_on_the_port_is_a_timeout(fob_emulator: FobFactory) -> None:
    dev = fob_emulator()
    dev.faults.inject("silence")
    tracker = FlockOfBirdsTracker(_config(dev.link.path, response_timeout_s=0.2))
    with pytest.raises(DeviceTimeoutError, match="EXAMINE VALUE 15"):
        tracker.open()


def test_missing_port_is_disconnected(tmp_path: Path) -> None:
    tracker = FlockOfBirdsTracker(_config(str(tmp_path / "ttyNONE")))
    with pytest.raises(DisconnectedError, match="cannot open serial port"):
        tracker.open()


def test_lifecycle() -> None:
    tracker = FlockOfBirdsTracker(_config("/dev/null"))
    with pytest.raises(LifecycleError):
        tracker.latest()
    assert tracker.sensors == ("stylus",)
    tracker.close()
    tracker.close()


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="standalone"):
        _config("/dev/x", sensors={"a": 0, "b": 1})
    with pytest.raises(ValueError, match="share"):
        _config("/dev/x", sensors={"a": 1, "b": 1})
    with pytest.raises(ValueError, match="dip-switch"):
        _config("/dev/x", baud_rate=12345)
    with pytest.raises(ValueError, match="Extra inputs"):
        _config("/dev/x", colour="red")


def test_point_mode_drops_a_damaged_reply(fob_emulator: FobFactory) -> None:
    dev = fob_emulator(n_birds=2)
    tracker = FlockOfBirdsTracker(_config(dev.link.path, sensors={"a": 1, "b": 2}, mode="point",
                                          max_step_mm=None))
    rec = Recorder()
    tracker.add_listener(rec)
    with tracker:
        dev.faults.inject("garbage,p=0.4,mask=0x7f")
        wait_until(lambda: rec.count("a") >= 15 and tracker.damaged_records >= 3, what="POINT replies")
    for s in rec.samples:
        _assert_matches(s, _truth(dev, "1" if s.sensor == "a" else "2"))


def test_fatal_error_register_fails_open(fob_emulator: FobFactory) -> None:
    from drivers.interfaces.errors import DeviceFaultError

    dev = fob_emulator()
    with dev.lock:
        dev.error_code = 2  # non-volatile storage write failure: FATAL
    tracker = FlockOfBirdsTracker(_config(dev.link.path))
    with pytest.raises(DeviceFaultError, match=r"Flock error 2 .*fatal"):
        tracker.open()
