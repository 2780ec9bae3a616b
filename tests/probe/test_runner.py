"""The probe's step runner, report and measurements, without devices."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from drivers.interfaces.camera import Frame, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, ProtocolError
from drivers.tracker_serial import probe_aurora
from hil.probe import Checklist, DeviceReport, Finding, Outcome, ProbeReport, Status, render_text
from hil.probe.camera import frame_checks


def test_steps_stop_at_the_first_failure_with_cause_and_hint() -> None:
    report = DeviceReport("tracker", "fob")
    cl = Checklist(report, timeout_s=1.0)
    assert cl.step("one", lambda: Outcome("first fine")) is not None

    def fails() -> Outcome:
        raise Finding("port /dev/ttyUSB9 does not exist", "plug it in", {"port": "/dev/ttyUSB9"})

    assert cl.step("two", fails) is None
    assert cl.step("three", lambda: Outcome("never run")) is None
    assert [c.name for c in report.checks] == ["one", "two"]
    assert report.checks[1].status is Status.FAIL
    assert report.checks[1].hint == "plug it in"
    assert report.checks[1].data == {"port": "/dev/ttyUSB9"}
    assert report.status is Status.FAIL
    assert report.stopped_early


def test_a_step_that_hangs_fails_after_its_timeout() -> None:
    release = threading.Event()
    report = DeviceReport("robot", "x")
    cl = Checklist(report, timeout_s=0.05)

    def hangs() -> Outcome:
        release.wait()
        return Outcome("too late")

    try:
        assert cl.step("connect", hangs, what="connecting to the arm") is None
    finally:
        release.set()
    assert report.checks[0].message == "connecting to the arm: no answer within 0.05 s"
    assert report.checks[0].status is Status.FAIL


def test_driver_errors_become_their_message_and_a_hint() -> None:
    report = DeviceReport("tracker", "aurora")
    cl = Checklist(report, timeout_s=1.0)

    def times_out() -> Outcome:
        raise DeviceTimeoutError("tracker", "no RESET within 7 s")

    cl.step("reset", times_out, what="resetting")
    assert report.checks[0].message == "resetting: no RESET within 7 s"
    assert "power" in report.checks[0].hint


@pytest.mark.parametrize("exc", [ProtocolError("tracker", "bad bytes"), ZeroDivisionError("boom")])
def test_no_exception_escapes_a_step(exc: Exception) -> None:
    report = DeviceReport("tracker", "plugin")
    cl = Checklist(report, timeout_s=1.0)

    def raises() -> Outcome:
        raise exc

    assert cl.step("x", raises) is None
    assert report.checks[0].status is Status.FAIL
    if isinstance(exc, ZeroDivisionError):
        assert report.checks[0].message == "x: unexpected ZeroDivisionError: boom"


def test_warnings_keep_exit_zero_and_failures_give_one() -> None:
    ok = DeviceReport("robot", "sim", simulated=True)
    Checklist(ok, 1.0).step("a", lambda: Outcome("fine"))
    warn = DeviceReport("camera", "sim", simulated=True)
    Checklist(warn, 1.0).step("b", lambda: Outcome("slow", Status.WARN, "lower the rate"))
    report = ProbeReport("s.toml", 1.0, [ok, warn])
    assert (report.status, report.exit_code) == (Status.WARN, 0)
    text = render_text(report)
    assert "  WARN  slow\n        try: lower the rate" in text
    assert text.endswith("summary: robot OK, camera WARN -> exit 0")
    failed = DeviceReport("tracker", "fob")
    Checklist(failed, 1.0).step("c", lambda: (_ for _ in ()).throw(Finding("gone")))
    assert ProbeReport("s.toml", 1.0, [ok, failed]).exit_code == 1


def _pair(t_ns: int, skew_ns: int, seq: int, size: tuple[int, int] = (64, 48)) -> StereoFrame:
    img = np.zeros((size[1], size[0]), np.uint8)
    return StereoFrame(Frame(img, t_ns, seq), Frame(img, t_ns + skew_ns, seq))


def test_frame_checks_measure_rate_skew_and_drops() -> None:
    period = 33_333_333
    seqs = [0, 1, 2, 4, 5, 8]  # 1 + 2 frames dropped
    skews_ms = [0.5, -1.0, 2.0, 0.0, 1.5, -0.5]
    pairs = [_pair(s * period, round(k * 1e6), s) for s, k in zip(seqs, skews_ms, strict=True)]
    checks = {c.name: c for c in frame_checks(pairs, (64, 48), 30.0)}
    assert checks["resolution"].status is Status.OK
    # 5 intervals over 8 periods, pair time = mean of left and right (skews +0.5 and -0.5 ms at the ends)
    span_s = (8 * period - 0.5e6) * 1e-9
    assert checks["frame_rate"].status is Status.WARN
    assert checks["frame_rate"].data["rate_hz"] == round(5 / span_s, 2) == 18.79
    assert checks["skew"].data == {"median_ms": 0.75, "max_ms": 2.0}
    assert checks["skew"].status is Status.OK
    assert checks["dropped_frames"].data["dropped"] == 3
    assert checks["dropped_frames"].status is Status.WARN


def test_frame_checks_flag_size_and_skew_problems() -> None:
    pairs = [_pair(k * 10_000_000, 8_000_000, k, (32, 24)) for k in range(5)]
    checks = {c.name: c for c in frame_checks(pairs, (64, 48), 100.0)}
    assert checks["resolution"].status is Status.WARN
    assert checks["resolution"].message == "images are 32x24 px, configured 64x48 px"
    assert checks["skew"].status is Status.WARN  # 8 ms > half of a 10 ms period
    assert checks["frame_rate"].status is Status.OK


class _Line:
    """A serial port stand-in that answers every command with one canned reply line."""

    def __init__(self, reply: bytes) -> None:
        self.reply = reply
        self.sent = b""

    def write(self, data: bytes) -> int:
        self.sent += data
        return len(data)

    def read_until(self, end: bytes) -> bytes:
        return self.reply

    def reset_input_buffer(self) -> None:
        pass


def test_aurora_probe_frames_commands_and_reads_replies_with_the_driver_codec() -> None:
    port = _Line(b"OKAYA896\r")  # reference A2.2: OKAY -> A896
    assert probe_aurora.command(port, "INIT:", 0.5) == "OKAY"
    assert port.sent == b"INIT:E3A5\r"


def test_aurora_probe_reply_with_a_bad_crc_or_an_error_code() -> None:
    with pytest.raises(probe_aurora.NdiError, match="fails its CRC") as bad:
        probe_aurora.command(_Line(b"RESETBE6E\r"), "VER:4", 0.5)
    assert bad.value.code is None
    with pytest.raises(probe_aurora.NdiError, match=r"^ERROR04$") as info:
        probe_aurora.command(_Line(b"ERROR046802\r"), "VER:4", 0.5)
    assert info.value.code == 0x04
    assert probe_aurora.answers(_Line(b"ERROR046802\r"), 9600, 0.5) == "(answers ERROR04)"
    assert probe_aurora.answers(_Line(b"RESETBE6E\r"), 9600, 0.5) is None
