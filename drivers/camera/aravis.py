"""Aravis stereo camera: two GigE Vision / USB3 Vision cameras through PyGObject, as one source.

Needs the ``aravis`` extra (PyGObject) and the Debian typelib ``gir1.2-aravis-0.8``
(``tools/setup_aravis.sh`` installs both).

Triggering (config ``trigger``):
- ``software``: TriggerSelector=FrameStart, TriggerMode=On, TriggerSource=Software; ``grab()``
  sends one TriggerSoftware to each camera and waits for that trigger's two frames.
- ``hardware``: TriggerSource=<trigger_line> on both cameras (one pulse drives both).
- ``free_run``: no trigger; the cameras stream at ``frame_rate_hz``.

Pairing (see :mod:`drivers.camera.pairing`): trigger id > device timestamps > nearest host time
within half a frame period. A frame's trigger id / frame index is its device frame id (GVSP block
id, unwrapped) counted from the side's first frame, which is given the trigger in flight when it
arrived (software trigger) or 1 (hardware trigger). Failed buffers still advance the count.

Timestamps: ``Frame.device_t_ns`` is the camera's timestamp (``arv_buffer_get_timestamp``, camera
clock, ns). The host reception time of the frame's first packet (``arv_buffer_get_system_timestamp``,
wall clock) is moved onto the controller clock by subtracting the frame's age at the moment it is
handed over. When the camera gives a timestamp, ``Frame.t_ns`` is that device time mapped to the
controller clock by an estimated offset -- the smallest ``reception - device time`` over the side's
last ``_OFFSET_WINDOW`` frames (the frame that travelled fastest; transfer jitter drops out, the
shortest transfer time stays in and ``hil rig-calibrate --temporal`` measures it) -- and
``Frame.time_source`` is ``exposure``; without one ``t_ns`` is the reception time
(``time_source = reception``).

Reconnection: a camera that stops answering (control channel lost, a trigger write failing, or
no pair for ``_TIMEOUTS_BEFORE_LOST`` grabs in a row) makes ``grab()`` raise
:class:`DisconnectedError` and starts a background reconnection: the old cameras are released and
both are opened again by their ids every ``_RECONNECT_RETRY_S`` until they answer (a GigE camera
that was power-cycled or restarted comes back with no stream destination and no controller, so
the old objects can never stream again). Meanwhile ``grab()`` waits up to its timeout for the
reconnection and raises :class:`DisconnectedError` (``reconnecting``) while it is not done; once
it is, the new cameras are swapped in (``aravis_reconnected``) and grabbing goes on. Only
``close()`` gives up.

Teardown: ``close()`` stops acquisition and drops the streams before the cameras; without that the
process can abort at exit (environment.md, Aravis).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

from drivers.camera.config import AravisCameraConfig
from drivers.camera.pairing import FrameIdUnwrapper, PairRule, Side, StereoPairer
from drivers.camera.pixels import PIXEL_FORMATS, PixelFormatError, to_mono8
from drivers.interfaces.camera import Frame, FrameTime, StereoCamera, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError, DriverError
from hil.clock import Clock
from hil.log import get_logger

if TYPE_CHECKING:
    from hil.vision.camera_model import StereoCalibration

log = get_logger(__name__)

#: Longest single blocking pop, s, so a lost control channel is noticed between pops.
_POP_SLICE_S = 0.05
#: Pause between two reconnection attempts, s.
_RECONNECT_RETRY_S = 0.5
#: Grabs in a row without a pair after which the stream counts as lost (reconnect).
_TIMEOUTS_BEFORE_LOST = 3
#: frames per side over which the device-to-controller clock offset is the smallest seen
_OFFSET_WINDOW = 100


class AravisUnavailableError(DriverError):
    """PyGObject or the Aravis typelib is not installed."""


def import_aravis(device: str = "camera") -> tuple[ModuleType, Any]:
    """Return ``(Aravis, GLib)`` from PyGObject.

    Raises:
        AravisUnavailableError: with what to install.
    """
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as exc:
        raise AravisUnavailableError(
            device,
            f"Aravis is not available ({exc}); install the 'aravis' extra (PyGObject==3.50.2) and the "
            "Debian packages gir1.2-aravis-0.8 libaravis-0.8-0 (tools/setup_aravis.sh does both)",
        ) from exc
    return Aravis, GLib


def resolve_pair_rule(config: AravisCameraConfig) -> PairRule:
    """The pairing rule the config asks for (``auto`` resolved by trigger mode)."""
    if config.pairing != "auto":
        return PairRule(config.pairing)
    if config.trigger == "software":
        return PairRule.TRIGGER_ID
    if config.trigger == "hardware":
        return PairRule.FRAME_ID
    return PairRule.DEVICE_TIME if config.device_clocks_synchronised else PairRule.HOST_TIME


@dataclass
class _Side:
    side: Side
    device_id: str
    camera: Any
    stream: Any = None
    unwrap: FrameIdUnwrapper = field(default_factory=FrameIdUnwrapper)
    lost_handler: int | None = None
    frames: int = 0
    failed_buffers: int = 0
    dead: bool = False  # control lost / a command failed: teardown does not talk to it
    # Set by Aravis' heartbeat thread on this side object only: a late emission from a camera
    # already handed to a reconnection marks the old object, never the cameras that replaced it.
    lost_reason: str = ""
    key_offset: int | None = None  # trigger id (or 1) of this side's first frame
    # reception (controller clock) minus device timestamp of the last frames: the clock mapping
    clock_offsets_ns: deque[int] = field(default_factory=lambda: deque(maxlen=_OFFSET_WINDOW))


@dataclass
class _Reconnect:
    """A background reconnection: ``sides`` is set (then ``ready``) when both cameras are open."""

    reason: str
    stop: threading.Event = field(default_factory=threading.Event)
    ready: threading.Event = field(default_factory=threading.Event)
    sides: dict[Side, _Side] | None = None
    attempts: int = 0
    error: str = ""
    thread: threading.Thread | None = None


class AravisStereoCamera(StereoCamera):
    """Two Aravis cameras as one :class:`StereoCamera`.

    Args:
        name: role name used in errors (``camera``).
        config: the validated ``[camera]`` section.
        clock: the controller clock; ``Frame.t_ns`` is on it.
        wall_clock_ns: the host wall clock Aravis' system timestamps use (injectable for tests).
    """

    def __init__(
        self,
        name: str,
        config: AravisCameraConfig,
        clock: Clock,
        *,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        super().__init__(name)
        self.config = config
        self._clock = clock
        self._wall_clock_ns = wall_clock_ns
        self._rule = resolve_pair_rule(config)
        self._pairer = StereoPairer(self._rule, round(1e9 / config.frame_rate_hz))
        self._sides: dict[Side, _Side] = {}
        self._stream_lost_reason = ""  # set by grab() after timeouts in a row: the next grab reconnects
        self._trigger_id = 0
        self._timeouts = 0  # grabs in a row that timed out
        self._reconnect: _Reconnect | None = None
        self.reconnections = 0
        self._aravis: ModuleType | None = None
        self._glib: Any = None

    # -- properties -------------------------------------------------------------------------
    @property
    def frame_rate_hz(self) -> float:
        return self.config.frame_rate_hz

    @property
    def calibration(self) -> StereoCalibration | None:
        """None: two GigE cameras know no stereo calibration; ``[calibration] stereo`` gives it."""
        return None

    @property
    def exposure_us(self) -> float:
        return self.config.exposure_us

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.config.width_px, self.config.height_px)

    @property
    def pair_rule(self) -> PairRule:
        return self._rule

    @property
    def stats(self) -> dict[str, int]:
        """Counters: frames received and failed buffers per side (since the last reconnection),
        frames dropped unpaired, frame-id offset re-learnings (hardware trigger), reconnections."""
        out = {"dropped_unpaired": self._pairer.dropped, "realigned": self._pairer.realigned,
               "reconnections": self.reconnections}
        for s in self._sides.values():
            out[f"{s.side}_frames"] = s.frames
            out[f"{s.side}_failed_buffers"] = s.failed_buffers
        return out

    # -- lifecycle --------------------------------------------------------------------------
    def _open(self) -> None:
        Aravis, GLib = import_aravis(self.name)
        self._aravis, self._glib = Aravis, GLib
        if self.config.enable_fake_interface:
            Aravis.enable_interface("Fake")
        try:
            wanted: tuple[tuple[Side, str], ...] = (("left", self.config.left_device_id),
                                                    ("right", self.config.right_device_id))
            for side, device_id in wanted:
                self._sides[side] = self._open_one(side, device_id)
            for s in self._sides.values():
                self._start(s)
        except BaseException:
            self._teardown()
            raise
        log.info("aravis_stereo_opened", device=self.name, left=self.config.left_device_id,
                 right=self.config.right_device_id, trigger=self.config.trigger, pairing=str(self._rule),
                 width_px=self.config.width_px, height_px=self.config.height_px,
                 frame_rate_hz=self.config.frame_rate_hz, exposure_us=self.config.exposure_us)

    def _open_one(self, side: Side, device_id: str) -> _Side:
        Aravis, GLib = self._aravis, self._glib
        assert Aravis is not None
        cfg = self.config
        try:
            camera = Aravis.Camera.new(device_id)
        except GLib.Error as exc:
            raise DisconnectedError(
                self.name, f"{side} camera {device_id!r} not found ({exc.message}); "
                "check the id/address with arv-tool-0.8"
            ) from exc
        state = _Side(side=side, device_id=device_id, camera=camera)
        try:
            camera.set_pixel_format_from_string(cfg.pixel_format)
            camera.set_region(cfg.offset_x_px, cfg.offset_y_px, cfg.width_px, cfg.height_px)
            # Frame rate first: Aravis turns FrameStart triggering off when it sets the rate.
            camera.set_frame_rate(cfg.frame_rate_hz)
            camera.set_exposure_time(cfg.exposure_us)
            if cfg.gain_db is not None:
                camera.set_gain(cfg.gain_db)
            if cfg.trigger == "software":
                camera.set_trigger("Software")
            elif cfg.trigger == "hardware":
                camera.set_trigger(cfg.trigger_line)
            else:
                camera.clear_triggers()
            camera.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
            if cfg.packet_size_bytes is not None and camera.is_gv_device():
                camera.gv_set_packet_size(cfg.packet_size_bytes)
            _x, _y, width, height = camera.get_region()
            if (width, height) != (cfg.width_px, cfg.height_px):
                raise DriverError(self.name, f"{side} camera {device_id!r} refused region "
                                             f"{cfg.width_px}x{cfg.height_px} (has {width}x{height})")
            stream = camera.create_stream(None, None)
        except GLib.Error as exc:
            raise DriverError(self.name, f"{side} camera {device_id!r}: configuration failed: "
                                         f"{exc.message}") from exc
        if stream is None:
            raise DisconnectedError(self.name, f"{side} camera {device_id!r}: no stream could be created")
        state.stream = stream
        payload = camera.get_payload()
        for _ in range(cfg.n_buffers):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        device = camera.get_device()
        state.lost_handler = device.connect("control-lost", self._on_control_lost, side, device_id)
        return state

    def _start(self, s: _Side) -> None:
        try:
            s.camera.start_acquisition()
        except self._glib.Error as exc:
            raise DisconnectedError(self.name, f"{s.side} camera {s.device_id!r}: acquisition did not "
                                               f"start: {exc.message}") from exc

    def _on_control_lost(self, device: Any, side: str, device_id: str) -> None:
        # Called from Aravis' heartbeat thread. A device already handed to a reconnection (its
        # handler disconnected while this emission waited for the GIL) or not in use yet is not
        # the current camera: ignored. The mark goes on this side's object only: if the grab
        # thread hands it to a reconnection meanwhile (``get_device`` releases the GIL), the mark
        # lands on the old object and the new cameras are not reconnected a second time.
        state = self._sides.get(side)  # type: ignore[call-overload]
        camera = None if state is None else state.camera
        if state is None or camera is None or camera.get_device() != device:
            log.info("aravis_control_lost_ignored", device=self.name, side=side, why="not the camera in use")
            return
        state.dead = True
        state.lost_reason = f"{side} camera {device_id!r}: control channel lost (no heartbeat answer)"

    def _close(self) -> None:
        stats = self.stats
        self._teardown()
        log.info("aravis_stereo_closed", device=self.name, **stats)

    def _teardown(self) -> None:
        """Stop a reconnection in progress, stop acquisition, then drop streams before cameras
        (avoids the abort at exit)."""
        job, self._reconnect = self._reconnect, None
        if job is not None:
            job.stop.set()
            if job.thread is not None:
                job.thread.join()
            if job.sides is not None:
                self._release(list(job.sides.values()))
        sides = list(self._sides.values())
        self._sides.clear()
        self._release(sides)

    def _release(self, sides: list[_Side], *, dead_in_background: bool = True) -> None:
        """Stop acquisition on the live ``sides``, disconnect their handlers, drop streams before
        cameras. Cameras that stopped answering are dropped on a background thread unless
        ``dead_in_background`` is False (the caller is a background thread itself)."""
        glib_error: type[BaseException] = self._glib.Error if self._glib is not None else RuntimeError
        for s in sides:
            if s.dead or s.camera is None:
                continue
            try:
                s.camera.stop_acquisition()
            except glib_error as exc:
                log.warning("aravis_stop_failed", device=self.name, side=s.side, error=str(exc))
        for s in sides:
            if s.lost_handler is not None and s.camera is not None:
                s.camera.get_device().disconnect(s.lost_handler)
                s.lost_handler = None
        dead = [(s.stream, s.camera) for s in sides if s.dead]
        for s in sides:
            s.stream = None
        for s in sides:
            s.camera = None
        if dead and dead_in_background:
            # Finalising an unreachable GigE device waits for GVCP write timeouts (~10 s: stream
            # channel close, leave control). Do it off the caller's thread; the thread is not a
            # daemon, so the interpreter still finishes it before exiting (no abort at exit).
            threading.Thread(target=_release_later, args=(dead,), name="aravis-teardown").start()
        elif dead:
            _release_later(dead)
        dead = []

    # -- reconnection -----------------------------------------------------------------------
    def _start_reconnect(self, reason: str) -> None:
        """Hand the current cameras to a background thread that releases them and opens both
        cameras again (every ``_RECONNECT_RETRY_S`` until they answer or ``close()``)."""
        old = list(self._sides.values())
        self._sides = {}
        for s in old:  # no more control-lost callbacks from the old devices
            if s.lost_handler is not None and s.camera is not None:
                s.camera.get_device().disconnect(s.lost_handler)
                s.lost_handler = None
        self._stream_lost_reason = ""
        job = _Reconnect(reason)
        # A daemon: it retries until close() stops it, and must not keep a process that forgot
        # close() alive forever.
        job.thread = threading.Thread(target=self._reconnect_loop, args=(old, job), name="aravis-reconnect",
                                      daemon=True)
        self._reconnect = job
        log.warning("aravis_reconnecting", device=self.name, reason=reason)
        job.thread.start()

    def _reconnect_loop(self, old: list[_Side], job: _Reconnect) -> None:
        # Background thread: the grab thread does not touch Aravis while the job runs.
        self._release(old, dead_in_background=False)  # before taking control again
        wanted: tuple[tuple[Side, str], ...] = (("left", self.config.left_device_id),
                                                ("right", self.config.right_device_id))
        while not job.stop.is_set():
            job.attempts += 1
            sides: dict[Side, _Side] = {}
            try:
                for side, device_id in wanted:
                    sides[side] = self._open_one(side, device_id)
                for st in sides.values():
                    self._start(st)
            except DriverError as exc:
                job.error = exc.message
                for st in sides.values():
                    st.dead = True  # it may not answer: never block on it here
                self._release(list(sides.values()), dead_in_background=False)
                job.stop.wait(_RECONNECT_RETRY_S)
                continue
            job.sides = sides
            job.ready.set()
            return

    def _finish_reconnect(self, timeout_s: float) -> None:
        """In ``grab()``: wait up to ``timeout_s`` for a reconnection in progress; swap the new
        cameras in, or raise DisconnectedError while it is not done."""
        job = self._reconnect
        if job is None:
            return
        if not job.ready.wait(max(timeout_s, 0.0)) or job.sides is None:
            detail = f" (attempt {job.attempts}: {job.error})" if job.error else ""
            raise DisconnectedError(self.name, f"{job.reason}; reconnecting{detail}")
        if job.thread is not None:
            job.thread.join()
        self._reconnect = None
        self._sides = job.sides
        self._pairer = StereoPairer(self._rule, round(1e9 / self.config.frame_rate_hz))
        self._timeouts = 0
        self.reconnections += 1
        log.info("aravis_reconnected", device=self.name, attempts=job.attempts, reason=job.reason,
                 reconnections=self.reconnections)

    # -- acquisition ------------------------------------------------------------------------
    def grab(self, timeout_s: float) -> StereoFrame:
        """Block until the next synchronised pair (see the module doc for the pair rule).

        Raises:
            LifecycleError: not active.
            DeviceTimeoutError: no pair within ``timeout_s`` (says which side had no frame).
            DisconnectedError: a camera's control channel was lost or a trigger failed (a
                reconnection starts), or a reconnection is still in progress.
        """
        self.require_active("grab")
        deadline = time.monotonic() + timeout_s
        self._finish_reconnect(timeout_s)
        self._check_lost()
        try:
            pair = self._grab(deadline, timeout_s)
        except DeviceTimeoutError as exc:
            self._timeouts += 1
            if self._timeouts >= _TIMEOUTS_BEFORE_LOST:
                self._stream_lost_reason = f"stream lost: {exc.message} ({self._timeouts} grabs in a row)"
            raise
        self._timeouts = 0
        return pair

    def _grab(self, deadline: float, timeout_s: float) -> StereoFrame:
        min_key: int | None = None
        if self.config.trigger == "software":
            self._trigger_id += 1
            min_key = self._trigger_id
            for s in self._sides.values():
                try:
                    s.camera.software_trigger()
                except self._glib.Error as exc:
                    s.dead = True
                    reason = f"{s.side} camera {s.device_id!r}: software trigger failed: {exc.message}"
                    self._start_reconnect(reason)
                    raise DisconnectedError(self.name, reason) from exc
        while True:
            for s in self._sides.values():
                self._drain(s)
            pair = self._pairer.pop_pair(min_key=min_key)
            if pair is not None:
                return pair
            self._check_lost()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeoutError(self.name, self._timeout_message(timeout_s))
            # Wait on the side that has fewer frames waiting.
            s = min(self._sides.values(), key=lambda x: self._pairer.pending(x.side))
            buffer = s.stream.timeout_pop_buffer(int(min(remaining, _POP_SLICE_S) * 1e6))
            if buffer is not None:
                self._handle(s, buffer)

    def _timeout_message(self, timeout_s: float) -> str:
        waiting = [s for s in self._sides.values() if self._pairer.pending(s.side) == 0]
        what = (", ".join(f"{s.side} camera {s.device_id!r}" for s in waiting) or "both cameras (unpaired)")
        trig = f" after software trigger {self._trigger_id}" if self.config.trigger == "software" else ""
        return f"no stereo pair within {timeout_s:g} s{trig}: no frame from {what}"

    def _check_lost(self) -> None:
        """Raise DisconnectedError (and start reconnecting) when a camera in use was lost: its
        control channel (marked on its side object) or the stream (timeouts in a row)."""
        reason = self._stream_lost_reason or next(
            (s.lost_reason for s in self._sides.values() if s.lost_reason), "")
        if reason:
            self._start_reconnect(reason)
            raise DisconnectedError(self.name, reason)

    def _drain(self, s: _Side) -> None:
        while True:
            buffer = s.stream.try_pop_buffer()
            if buffer is None:
                return
            self._handle(s, buffer)

    def _handle(self, s: _Side, buffer: Any) -> None:
        """Turn one popped buffer into a frame for the pairer; always gives the buffer back."""
        Aravis = self._aravis
        assert Aravis is not None
        try:
            raw_id = int(buffer.get_frame_id())
            index = s.unwrap(raw_id) if raw_id != 0 else None
            if index is not None and s.key_offset is None:
                # Software trigger: the first frame answers the trigger in flight (so a first
                # trigger lost entirely does not shift every later pair). Else count from 1.
                s.key_offset = self._trigger_id if self.config.trigger == "software" else 1
            if buffer.get_status() != Aravis.BufferStatus.SUCCESS:
                s.failed_buffers += 1
                log.warning("aravis_buffer_failed", device=self.name, side=s.side,
                            status=buffer.get_status().value_nick, frame_id=raw_id)
                return
            if index is None:
                s.failed_buffers += 1
                return
            width, height = buffer.get_image_width(), buffer.get_image_height()
            try:
                image = to_mono8(buffer.get_data(), width, height, int(buffer.get_image_pixel_format()))
            except PixelFormatError as exc:
                s.failed_buffers += 1
                log.warning("aravis_bad_payload", device=self.name, side=s.side, frame_id=raw_id,
                            error=str(exc))
                return
            age_ns = max(0, self._wall_clock_ns() - int(buffer.get_system_timestamp()))
            reception_ns = self._clock.now_ns() - age_ns
            device_ns = int(buffer.get_timestamp())
            t_ns, source = reception_ns, FrameTime.RECEPTION
            if device_ns > 0:  # the device's (exposure) time, mapped onto the controller clock
                s.clock_offsets_ns.append(reception_ns - device_ns)
                t_ns, source = device_ns + min(s.clock_offsets_ns), FrameTime.EXPOSURE
            frame = Frame(image=image, t_ns=t_ns, seq=index, device_t_ns=device_ns, time_source=source)
            s.frames += 1
            self._pairer.push(s.side, frame, key=index + (s.key_offset or 1))
        finally:
            s.stream.push_buffer(buffer)


def _release_later(objects: list[tuple[Any, Any]]) -> None:
    """Drop the last references (stream before camera) of cameras that stopped answering."""
    while objects:
        stream, camera = objects.pop()
        del stream
        del camera


__all__ = ["PIXEL_FORMATS", "AravisStereoCamera", "AravisUnavailableError", "import_aravis",
           "resolve_pair_rule"]
