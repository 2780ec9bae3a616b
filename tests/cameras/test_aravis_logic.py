"""The Aravis driver's logic against a scripted stand-in for the Aravis/GLib modules.

The real transport is covered by test_aravis_gige.py; here the cases a fake GigE camera cannot
produce on demand: failed buffers, a frame arriving a trigger late, the 16-bit frame-id wrap,
a lost control channel, a refused region, a failing trigger write.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pytest

import drivers.camera.aravis as aravis_mod
from drivers.camera.aravis import AravisStereoCamera
from drivers.camera.config import AravisCameraConfig
from drivers.camera.pixels import MONO_8, MONO_16
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError, DriverError
from hil.clock import ManualClock

W, H = 4, 2
WALL_NS = 1_000_000_000_000


class GLibError(Exception):
    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class StubGLib:
    Error = GLibError


@dataclass(frozen=True)
class Status:
    value_nick: str


class StubAravis:
    class BufferStatus:
        SUCCESS = Status("success")
        MISSING_PACKETS = Status("missing-packets")

    class AcquisitionMode:
        CONTINUOUS = 1

    class Buffer:
        @staticmethod
        def new_allocate(size: int) -> None:
            return None

    cameras: ClassVar[dict[str, StubCamera]] = {}

    class Camera:
        @staticmethod
        def new(device_id: str) -> StubCamera:
            if device_id not in StubAravis.cameras:
                raise GLibError(f"Device '{device_id}' not found")
            return StubAravis.cameras[device_id]

    @staticmethod
    def enable_interface(name: str) -> None:
        pass


@dataclass
class StubBuffer:
    frame_id: int
    value: int
    status: Status = StubAravis.BufferStatus.SUCCESS
    pixel_format: int = MONO_8
    device_ts_ns: int = 0
    system_ts_ns: int = WALL_NS - 2_000_000

    def get_frame_id(self) -> int:
        return self.frame_id

    def get_status(self) -> Status:
        return self.status

    def get_image_width(self) -> int:
        return W

    def get_image_height(self) -> int:
        return H

    def get_image_pixel_format(self) -> int:
        return self.pixel_format

    def get_data(self) -> bytes:
        if self.pixel_format == MONO_16:
            return np.full(W * H, self.value * 256, dtype="<u2").tobytes()
        return bytes([self.value]) * (W * H)

    def get_timestamp(self) -> int:
        return self.device_ts_ns

    def get_system_timestamp(self) -> int:
        return self.system_ts_ns


@dataclass
class StubStream:
    queue: deque[StubBuffer] = field(default_factory=deque)
    returned: int = 0

    def push_buffer(self, buffer: StubBuffer | None) -> None:
        if buffer is not None:
            self.returned += 1

    def try_pop_buffer(self) -> StubBuffer | None:
        return self.queue.popleft() if self.queue else None

    def timeout_pop_buffer(self, timeout_us: int) -> StubBuffer | None:
        return self.try_pop_buffer()


@dataclass
class StubDevice:
    handlers: list[tuple[Callable[..., None], tuple[Any, ...]]] = field(default_factory=list)

    def connect(self, signal: str, handler: Callable[..., None], *args: Any) -> int:
        assert signal == "control-lost"
        self.handlers.append((handler, args))
        return len(self.handlers)

    def disconnect(self, handler_id: int) -> None:
        pass

    def lose_control(self) -> None:
        for handler, args in self.handlers:
            handler(self, *args)


@dataclass
class StubCamera:
    """``script(trigger_count)`` returns the buffers a TriggerSoftware makes arrive."""

    script: Callable[[int], list[StubBuffer]]
    region: tuple[int, int, int, int] = (0, 0, W, H)
    trigger_fails: bool = False
    stream: StubStream = field(default_factory=StubStream)
    device: StubDevice = field(default_factory=StubDevice)
    calls: list[str] = field(default_factory=list)
    triggers: int = 0

    def __getattr__(self, name: str) -> Callable[..., Any]:
        # set_pixel_format_from_string, set_frame_rate, set_trigger, ...: record the call.
        def record(*args: Any) -> None:
            self.calls.append(f"{name}{args}")
        return record

    def is_gv_device(self) -> bool:
        return True

    def get_region(self) -> tuple[int, int, int, int]:
        return self.region

    def create_stream(self, callback: Any, data: Any) -> StubStream:
        return self.stream

    def get_payload(self) -> int:
        return W * H

    def get_device(self) -> StubDevice:
        return self.device

    def software_trigger(self) -> None:
        if self.trigger_fails:
            raise GLibError("[TriggerSoftware] GigEVision write_register timeout")
        self.triggers += 1
        self.stream.queue.extend(self.script(self.triggers))


@pytest.fixture
def stub_aravis(monkeypatch: pytest.MonkeyPatch) -> type[StubAravis]:
    StubAravis.cameras = {}
    monkeypatch.setattr(aravis_mod, "import_aravis", lambda device="camera": (StubAravis, StubGLib))
    return StubAravis


def config(**kw: Any) -> AravisCameraConfig:
    base: dict[str, Any] = {"driver": "aravis", "left_device_id": "L", "right_device_id": "R",
                            "width_px": W, "height_px": H, "frame_rate_hz": 50.0}
    base.update(kw)
    return AravisCameraConfig(**base)


def one_per_trigger(first_id: int, value0: int = 0, **kw: Any) -> Callable[[int], list[StubBuffer]]:
    def script(k: int) -> list[StubBuffer]:
        return [StubBuffer(frame_id=(first_id - 1 + k - 1) % 65535 + 1, value=value0 + k, **kw)]
    return script


def make(stub: type[StubAravis], left: StubCamera, right: StubCamera, **kw: Any) -> AravisStereoCamera:
    stub.cameras = {"L": left, "R": right}
    return AravisStereoCamera("camera", config(**kw), ManualClock(start_ns=9_000_000_000),
                              wall_clock_ns=lambda: WALL_NS)


def test_software_trigger_pairs_across_the_frame_id_wrap(stub_aravis: type[StubAravis]) -> None:
    left = StubCamera(one_per_trigger(65534, device_ts_ns=5))
    right = StubCamera(one_per_trigger(100, value0=50, pixel_format=MONO_16, device_ts_ns=7))
    cam = make(stub_aravis, left, right)
    cam.open()
    pairs = [cam.grab(1.0) for _ in range(4)]
    assert [(p.left.seq, p.right.seq) for p in pairs] == [(0, 0), (1, 1), (2, 2), (3, 3)]
    assert [int(p.left.image[0, 0]) for p in pairs] == [1, 2, 3, 4]
    assert [int(p.right.image[0, 0]) for p in pairs] == [51, 52, 53, 54]  # Mono16 -> top 8 bits
    assert pairs[0].left.image.shape == (H, W)
    # t_ns = clock now - (wall now - reception time): received 2 ms ago.
    assert pairs[0].left.t_ns == 9_000_000_000 - 2_000_000
    assert (pairs[0].left.device_t_ns, pairs[0].right.device_t_ns) == (5, 7)
    assert "set_trigger('Software',)" in left.calls
    assert left.calls.index("set_frame_rate(50.0,)") < left.calls.index("set_trigger('Software',)")
    assert left.stream.returned == 4  # every buffer goes back to the stream
    cam.close()
    assert "stop_acquisition()" in left.calls
    assert "stop_acquisition()" in right.calls


def test_failed_buffer_is_counted_never_returned(stub_aravis: type[StubAravis]) -> None:
    def right_script(k: int) -> list[StubBuffer]:
        status = StubAravis.BufferStatus.MISSING_PACKETS if k == 2 else StubAravis.BufferStatus.SUCCESS
        return [StubBuffer(frame_id=10 + k, value=k, status=status)]

    cam = make(stub_aravis, StubCamera(one_per_trigger(1)), StubCamera(right_script))
    cam.open()
    assert cam.grab(1.0).right.seq == 0
    with pytest.raises(DeviceTimeoutError, match="after software trigger 2: no frame from right camera 'R'"):
        cam.grab(0.01)
    pair = cam.grab(1.0)
    assert (pair.left.seq, pair.right.seq) == (2, 2)  # the failed buffer still counted: ids stay aligned
    assert cam.stats["right_failed_buffers"] == 1
    cam.close()


def test_a_frame_arriving_a_trigger_late_is_not_returned_as_fresh(stub_aravis: type[StubAravis]) -> None:
    def late_left(k: int) -> list[StubBuffer]:
        if k == 2:
            return []
        if k == 3:
            return [StubBuffer(frame_id=2, value=2), StubBuffer(frame_id=3, value=3)]
        return [StubBuffer(frame_id=k, value=k)]

    cam = make(stub_aravis, StubCamera(late_left), StubCamera(one_per_trigger(1, value0=100)))
    cam.open()
    cam.grab(1.0)
    with pytest.raises(DeviceTimeoutError, match="no frame from left camera 'L'"):
        cam.grab(0.01)
    pair = cam.grab(1.0)
    assert (int(pair.left.image[0, 0]), int(pair.right.image[0, 0])) == (3, 103)
    assert cam.stats["dropped_unpaired"] == 2  # trigger 2's frames
    cam.close()


def test_first_trigger_lost_entirely_does_not_shift_the_pairs(stub_aravis: type[StubAravis]) -> None:
    def left_script(k: int) -> list[StubBuffer]:
        return [] if k == 1 else [StubBuffer(frame_id=40 + k, value=k)]

    cam = make(stub_aravis, StubCamera(left_script), StubCamera(one_per_trigger(1, value0=100)))
    cam.open()
    with pytest.raises(DeviceTimeoutError):
        cam.grab(0.01)
    pair = cam.grab(1.0)
    assert (int(pair.left.image[0, 0]), int(pair.right.image[0, 0])) == (2, 102)
    cam.close()


def test_lost_control_channel_is_disconnected_error(stub_aravis: type[StubAravis]) -> None:
    left, right = StubCamera(one_per_trigger(1)), StubCamera(one_per_trigger(1))
    cam = make(stub_aravis, left, right)
    cam.open()
    cam.grab(1.0)
    del stub_aravis.cameras["R"]  # gone for good: the reconnection keeps failing
    right.device.lose_control()
    with pytest.raises(DisconnectedError, match="right camera 'R': control channel lost"):
        cam.grab(1.0)
    reconnecting = r"control channel lost \(no heartbeat answer\); reconnecting \(attempt \d+: .*'R' not"
    with pytest.raises(DisconnectedError, match=reconnecting):
        cam.grab(0.2)
    cam.close()
    assert "stop_acquisition()" in left.calls
    assert "stop_acquisition()" not in right.calls  # a dead camera is not talked to


def test_cameras_that_come_back_are_reconnected(stub_aravis: type[StubAravis]) -> None:
    """A restarted GigE camera has no stream destination and no controller: the driver releases
    the old objects and opens the cameras again; grabbing goes on with the new ones."""
    left, right = StubCamera(one_per_trigger(1)), StubCamera(one_per_trigger(1))
    cam = make(stub_aravis, left, right)
    cam.open()
    cam.grab(1.0)
    new_left, new_right = StubCamera(one_per_trigger(7, value0=10)), StubCamera(one_per_trigger(9, value0=20))
    stub_aravis.cameras = {"L": new_left, "R": new_right}
    left.device.lose_control()
    with pytest.raises(DisconnectedError, match="left camera 'L': control channel lost"):
        cam.grab(1.0)
    pair = cam.grab(5.0)  # waits for the reconnection, then grabs from the new cameras
    assert (int(pair.left.image[0, 0]), int(pair.right.image[0, 0])) == (11, 21)
    assert (pair.left.seq, pair.right.seq) == (0, 0)
    assert cam.grab(1.0).left.seq == 1
    assert cam.stats["reconnections"] == 1
    assert "stop_acquisition()" in right.calls  # the live old camera was stopped before reopening
    assert "start_acquisition()" in new_left.calls
    cam.close()
    assert "stop_acquisition()" in new_left.calls


def test_a_late_heartbeat_from_a_camera_being_replaced_does_not_reconnect_again(
        stub_aravis: type[StubAravis]) -> None:
    """Both cameras stop answering; the right's heartbeat loss starts the reconnection while the
    left's emission is inside ``get_device()`` (PyGObject releases the GIL there, so the grab thread
    runs). The left's mark must land on the camera handed away, not on the ones that replace it:
    one outage, one reconnection (the flake seen in the fake-GigE stream-loss test)."""
    left, right = StubCamera(one_per_trigger(1)), StubCamera(one_per_trigger(1))
    cam = make(stub_aravis, left, right)
    cam.open()
    cam.grab(1.0)
    stub_aravis.cameras = {"L": StubCamera(one_per_trigger(1, value0=10)),
                           "R": StubCamera(one_per_trigger(1, value0=20))}
    right.device.lose_control()
    raised: list[str] = []

    class GrabWhileInGetDevice(StubDevice):
        armed = True

        def __eq__(self, other: object) -> bool:  # the handler's comparison: the grab thread runs here
            if GrabWhileInGetDevice.armed:
                GrabWhileInGetDevice.armed = False
                with pytest.raises(DisconnectedError) as info:
                    cam.grab(1.0)
                raised.append(info.value.message)
            return other is self

        __hash__ = object.__hash__

    late = GrabWhileInGetDevice(handlers=left.device.handlers)
    left.device = late
    late.lose_control()
    assert raised == ["right camera 'R': control channel lost (no heartbeat answer)"]
    pair = cam.grab(5.0)  # the reconnection's new cameras
    assert (int(pair.left.image[0, 0]), int(pair.right.image[0, 0])) == (11, 21)
    assert int(cam.grab(1.0).left.image[0, 0]) == 12  # no second "control channel lost"
    assert cam.stats["reconnections"] == 1
    cam.close()


def test_grabs_timing_out_in_a_row_count_as_a_lost_stream(stub_aravis: type[StubAravis]) -> None:
    silent = StubCamera(lambda k: [])
    cam = make(stub_aravis, StubCamera(one_per_trigger(1)), silent)
    cam.open()
    for _ in range(3):
        with pytest.raises(DeviceTimeoutError):
            cam.grab(0.01)
    stub_aravis.cameras = {"L": StubCamera(one_per_trigger(1)), "R": StubCamera(one_per_trigger(1, value0=5))}
    lost = r"stream lost: .*no frame from right camera 'R' \(3 grabs in a row\)"
    with pytest.raises(DisconnectedError, match=lost):
        cam.grab(1.0)
    assert int(cam.grab(5.0).right.image[0, 0]) == 6
    cam.close()


def test_failing_trigger_write_is_disconnected_error(stub_aravis: type[StubAravis]) -> None:
    right = StubCamera(one_per_trigger(1), trigger_fails=True)
    cam = make(stub_aravis, StubCamera(one_per_trigger(1)), right)
    cam.open()
    with pytest.raises(DisconnectedError, match="right camera 'R': software trigger failed"):
        cam.grab(1.0)
    cam.close()


def test_unknown_camera_and_refused_region(stub_aravis: type[StubAravis]) -> None:
    left = StubCamera(one_per_trigger(1))
    stub_aravis.cameras = {"L": left}
    cam = AravisStereoCamera("camera", config(), ManualClock())
    with pytest.raises(DisconnectedError, match="camera: right camera 'R' not found"):
        cam.open()
    refused = StubCamera(one_per_trigger(1), region=(0, 0, 2, 2))
    cam = make(stub_aravis, StubCamera(one_per_trigger(1)), refused)
    with pytest.raises(DriverError, match=f"right camera 'R' refused region {W}x{H} \\(has 2x2\\)"):
        cam.open()


def test_free_run_and_hardware_trigger_settings(stub_aravis: type[StubAravis]) -> None:
    left, right = StubCamera(one_per_trigger(1)), StubCamera(one_per_trigger(1))
    cam = make(stub_aravis, left, right, trigger="hardware", trigger_line="Line1", packet_size_bytes=8000)
    cam.open()
    assert "set_trigger('Line1',)" in left.calls
    assert "gv_set_packet_size(8000,)" in left.calls
    cam.close()
    left, right = StubCamera(one_per_trigger(1)), StubCamera(one_per_trigger(1))
    cam = make(stub_aravis, left, right, trigger="free_run")
    cam.open()
    assert "clear_triggers()" in left.calls
    cam.close()


def test_device_timestamps_are_mapped_by_the_fastest_transfer(stub_aravis: type[StubAravis]) -> None:
    """t_ns = device time + min(reception - device time) so far: the transfer jitter drops out,
    the shortest transfer stays."""
    delays_ms = [5.0, 2.0, 7.0, 3.0]   # reception - exposure of frames 1..4, one second apart

    def script(ts0: int) -> Callable[[int], list[StubBuffer]]:
        def s(k: int) -> list[StubBuffer]:
            return [StubBuffer(frame_id=k, value=k, device_ts_ns=ts0 + k * 1_000_000_000,
                               system_ts_ns=WALL_NS - (4 - k) * 1_000_000_000 + round(delays_ms[k - 1] * 1e6)
                               - 10_000_000)]
        return s

    cam = make(stub_aravis, StubCamera(script(10**12)), StubCamera(script(5 * 10**12)))
    cam.open()
    pairs = [cam.grab(1.0) for _ in range(4)]
    # exposure of frame k on the controller clock: its reception minus its delay
    exposure = [9_000_000_000 - 10_000_000 - (4 - k) * 1_000_000_000 for k in range(1, 5)]
    assert [p.left.t_ns - e for p, e in zip(pairs, exposure, strict=True)] == [5_000_000, 2_000_000,
                                                                                 2_000_000, 2_000_000]
    assert all(p.left.time_source.value == "exposure" for p in pairs)
    cam.close()
