"""Perception in its own process: grab, locate, triangulate, publish into the marker ring.

Parent side: :class:`PerceptionProcess`. It creates the shared ring (:mod:`hil.perception.ring`),
a notification pipe and a channel (socket pair), starts the child (``python -m
hil.perception.child``: a fresh interpreter, as the servo process), sends it the spec and waits
for its ready report. Spawning, the ready handshake, liveness and ending the child are
:class:`hil.childproc.ChildProcess`'s, shared with the servo process. It is also the consumer
the controller's pipeline reads pairs from, with the shape of
:class:`~hil.controller.prefetch.FramePrefetcher`: :meth:`~PerceptionProcess.ready`,
:meth:`~PerceptionProcess.take` and :meth:`~PerceptionProcess.stop`.

Child side: :func:`hil.perception.worker.perception_main` builds the setup's camera through the
driver registry on the wall clock, the marker locator on the setup's calibration, and loops: grab,
locate, publish, one byte down the notification pipe.

What crosses the boundary: the spec (the validated setup, the servo's state-ring name, the
simulated world's time origin) and breath-hold requests go down the channel; marker sets and
error records come back through the ring; the ready report, a start failure and a crash's
traceback come back on the channel. Images never cross: the supervisor gets each pair's
timestamps, counters, time source, image size and located markers, and a :class:`StereoFrame`
whose images are empty (0 x 0) stands for the pair.

Shutdown and failures:

- ``close``: the child closes its camera and exits (the parent waits, then terminates, then kills);
  the ring's segment is unlinked.
- the parent dies: the child's channel ends (or its parent changes, checked every pair): it closes
  the camera and exits.
- the camera raises on a grab: an error record; :meth:`PerceptionProcess.take` raises the same
  driver error class with the camera's name and message. Locating raises: the record carries the
  error, and the pipeline raises :class:`PerceptionLocateError` where it would have located.
- the child crashes or exits: :meth:`~PerceptionProcess.take` raises DisconnectedError naming the
  camera and why (exit code, or the crash's last line).

The child ignores SIGINT: Ctrl-C goes to the whole process group, and the parent decides.
"""

from __future__ import annotations

import contextlib
import os
import select
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.interfaces.camera import Frame, FrameTime, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError
from hil import childproc
from hil.childproc import ChildProcess
from hil.config.setup import SetupConfig
from hil.controller.located import LocatedMarkers
from hil.controller.prefetch import WAKE_POLL_S, Prefetched
from hil.errors import HilError
from hil.perception.ring import MarkerRecord, MarkerRing, RecordKind, ring_words
from hil.servo.shm import ShmRegion
from hil.servo.wire import error_from_wire

#: How long the child may take to start (a fresh interpreter importing numpy, the driver, the
#: locator).
START_TIMEOUT_S = childproc.START_TIMEOUT_S
#: Locate times kept for the figures (the newest).
LOCATE_SAMPLES = 4096
#: The longest a waiting ``take`` goes without checking that the child still runs, s.
ALIVE_CHECK_S = 0.05

_NO_IMAGE = np.zeros((0, 0), dtype=np.uint8)
_NO_IMAGE.setflags(write=False)
_SOURCES = tuple(FrameTime)


class PerceptionLocateError(HilError):
    """Locating the markers of a pair raised in the perception process: ``ClassName: message``
    of the original error (the controller faults on it as on a locate error in-process)."""


@dataclass(frozen=True)
class PerceptionSpec:
    """What the child needs (picklable).

    Attributes:
        setup: the validated setup (its camera section is built in the child).
        servo_ring: the servo process's state-ring segment name, for a simulated world to see
            the arm there (None: no servo process, the world sees its own robot).
        T_flange_from_tcp: 4x4 (mm) of the robot, to turn the ring's TCP poses into flange poses.
        world_t0_ns: the supervisor's simulated world's time origin (the child's world uses the
            same, so the patient moves the same); None without a world.
        cpu: the CPU to keep the child on (None: every CPU but the servo loop's).
    """

    setup: SetupConfig
    servo_ring: str | None = None
    T_flange_from_tcp: tuple[tuple[float, ...], ...] | None = None
    world_t0_ns: int | None = None
    cpu: int | None = None


@dataclass(frozen=True)
class PerceptionReady:
    """What the child reports once its camera is open."""

    camera_name: str
    pid: int
    cpus: tuple[int, ...]
    #: when the child's camera had opened (``time.monotonic_ns``, the same clock in every process):
    #: the origin of its fault schedule, ``[[faults]] start_s`` (drivers/faults.py)
    opened_ns: int = 0


def frame_of(rec: MarkerRecord) -> StereoFrame:
    """The stand-in pair of a marker record: its timestamps, counters and time source, no image."""
    src = _SOURCES[rec.time_source] if 0 <= rec.time_source < len(_SOURCES) else FrameTime.EXPOSURE
    return StereoFrame(Frame(_NO_IMAGE, rec.left_t_ns, rec.left_seq, rec.left_device_t_ns, src),
                       Frame(_NO_IMAGE, rec.right_t_ns, rec.right_seq, rec.right_device_t_ns, src))


class PerceptionProcess:
    """Parent side of the perception process (module doc). ``start`` blocks until the child is
    ready; ``take`` blocks up to its timeout for the next marker set.

    Args:
        spec_for: makes the spec at :meth:`start` (the servo ring exists only once the servo
            process runs).
        camera_name: the camera's name, for the errors raised here.

    Attributes:
        produced: records taken or skipped so far (the ring's head when last read).
        overwritten: records replaced by a newer one before they were taken (latest wins).
        locate_ms: the locate time of the last :data:`LOCATE_SAMPLES` marker sets taken, ms.
        delivery_ms: the camera's latency of the same pairs (exposure -> handed over), ms.
    """

    def __init__(self, spec_for: Callable[[], PerceptionSpec], camera_name: str) -> None:
        self._spec_for = spec_for
        self.camera_name = camera_name
        self.ready_info: PerceptionReady | None = None
        self.produced = 0
        self.overwritten = 0
        self.locate_ms: deque[float] = deque(maxlen=LOCATE_SAMPLES)
        self.delivery_ms: deque[float] = deque(maxlen=LOCATE_SAMPLES)
        self._taken_head = 0
        self._crash: str | None = None
        self._child = ChildProcess("hil.perception.child", "perception process", camera_name, ("close",))

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> PerceptionReady:
        """Create the ring, the pipe and the channel, start the child, wait until it is ready.

        Raises:
            DriverError: building or opening the camera in the child raised (same class, device
                and message); DeviceTimeoutError when the child does not start in time;
                DisconnectedError when it exits before it is ready.
        """
        spec = self._spec_for()
        self.region = ShmRegion.create(ring_words())
        self.ring = MarkerRing(self.region)
        self._notify_r, notify_w = os.pipe()
        os.set_blocking(self._notify_r, False)
        try:
            self._conn = self._child.spawn(extra_fds=(notify_w,))
        except BaseException:
            os.close(self._notify_r)
            self.region.close()
            raise
        finally:
            os.close(notify_w)
        info = self._child.handshake(
            (spec, self.region.name), wait_ready=self._wait_ready,
            failed=lambda payload: error_from_wire(*payload),
            # the first (cold: caches, a full search) pair is published
            published=lambda: self.ring.head != 0, pause=self._wait_notified,
            unpublished="perception process published nothing after starting", on_failure=self.close)
        self.ready_info = PerceptionReady(str(info["camera_name"]), int(info["pid"]),
                                          tuple(int(c) for c in info["cpus"]), int(info["opened_ns"]))
        return self.ready_info

    def _wait_notified(self, timeout_s: float = ALIVE_CHECK_S) -> None:
        """Wait up to ``timeout_s`` for a notification (a record published); never raises."""
        with contextlib.suppress(OSError, ValueError):
            select.select([self._notify_r], [], [], timeout_s)

    def close(self, timeout_s: float = 5.0) -> None:
        """End the child (module doc), unlink the ring. Idempotent; never raises."""
        if not self._child.close(timeout_s):
            return
        with contextlib.suppress(OSError):
            os.close(self._notify_r)
        self.region.close()

    @property
    def pid(self) -> int | None:
        """The child's process id (None before start)."""
        return self._child.pid

    @property
    def exitcode(self) -> int | None:
        """The child's exit code (negative: the signal that ended it); None while it runs or
        before :meth:`start`."""
        return self._child.exitcode

    def gone(self) -> str | None:
        """None while the child runs; else why it is gone."""
        if not self._child.started:
            return "perception process not started"
        if self._child.closed:
            return "perception process closed"
        self._pump(0.0)
        return self._gone_now()

    def _gone_now(self) -> str | None:
        """The crash the child reported, else its exit (None while it runs). Never blocks."""
        if self._crash is not None:
            return self._crash
        return None if self._child.running else self._child.exited()

    def relay_breath_hold(self, start_s: float, duration_s: float, level: float) -> None:
        """Tell the child's simulated world about a breath-hold (world time ``start_s``). Never
        blocks for long, never raises (a gone child is reported by ``take``)."""
        if self._child.started and not self._child.closed:
            self._child.send_quietly(("hold", start_s, duration_s, level))

    def relay_servo_ring(self, ring_name: str) -> None:
        """Tell the child's simulated world to follow the arm through the state ring ``ring_name``
        (a restarted servo process's: the old ring is gone with the old loop). Never blocks for
        long, never raises (a gone child is reported by ``take``)."""
        if self._child.started and not self._child.closed:
            self._child.send_quietly(("follow", ring_name))

    def locate_figures(self) -> dict[str, float | None]:
        """p50 and p95 of the locate time in the perception process, ms (None before a pair), as
        :meth:`hil.controller.perception.StereoMarkerLocator.locate_ms` gives them in-process."""
        if not self.locate_ms:
            return {"p50": None, "p95": None}
        a = np.fromiter(self.locate_ms, dtype=np.float64)
        return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95))}

    def delivery_figures(self) -> dict[str, float | None]:
        """p50 and p99 of the camera's own latency, ms: the left frame's exposure -> the camera
        handed the pair to the perception process (pairs stamped at exposure only; None before
        one)."""
        if not self.delivery_ms:
            return {"p50": None, "p99": None}
        a = np.fromiter(self.delivery_ms, dtype=np.float64)
        return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))}

    # ------------------------------------------------------------------ consumer contract
    def ready(self) -> bool:
        """Whether :meth:`take` would return at once (a record not taken yet). Never blocks."""
        return self._child.started and not self._child.closed and self.ring.head > self._taken_head

    def take(self, timeout_s: float, wake: Callable[[], bool] | None = None) -> Prefetched | None:
        """The newest marker set not taken yet, waiting up to ``timeout_s`` for one (blocking).
        With ``wake``, checked every :data:`~hil.controller.prefetch.WAKE_POLL_S` while waiting:
        once it returns True, returns None at once. Older records not taken are skipped (counted
        in :attr:`overwritten`).

        Raises:
            DriverError: the camera raised on the newest grab (its class, device and message).
            DisconnectedError: the perception process is gone (names the camera and why).
            DeviceTimeoutError: no record within ``timeout_s`` (names the camera).
        """
        if self._child.closed or not self._child.started:
            raise DisconnectedError(self.camera_name, str(self.gone()))
        deadline = time.monotonic() + timeout_s
        while True:
            got = self._take_new()
            if got is not None:
                return got
            if wake is not None and wake():
                return None
            why = self.gone()
            if why is not None:
                got = self._take_new()   # what it published before it went
                if got is not None:
                    return got
                raise DisconnectedError(self.camera_name, why)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeoutError(self.camera_name, f"no stereo pair within {timeout_s} s")
            step_s = WAKE_POLL_S if wake is not None else ALIVE_CHECK_S
            self._wait_notified(min(remaining, ALIVE_CHECK_S, step_s))

    def stop(self, timeout_s: float | None = None) -> None:
        """Nothing to stop: the process runs until :meth:`close` (the prefetcher's contract)."""

    def _take_new(self) -> Prefetched | None:
        with contextlib.suppress(OSError):   # drain the notifications (non-blocking)
            while os.read(self._notify_r, 4096):
                pass
        head = self.ring.head
        if head <= self._taken_head:
            return None
        rec = self.ring.read_latest()
        assert rec is not None
        self.overwritten += head - self._taken_head - 1
        self._taken_head = head
        self.produced = head
        if rec.kind is RecordKind.GRAB_ERROR:
            assert rec.error is not None
            raise error_from_wire(*rec.error)
        if rec.kind is RecordKind.LOCATE_ERROR:
            assert rec.error is not None
            kind, _, message = rec.error
            return Prefetched(frame_of(rec), None, PerceptionLocateError(f"{kind}: {message}"), rec.pair_seq)
        frame = frame_of(rec)
        self.locate_ms.append(rec.locate_ms)
        if rec.time_source == 0:   # stamped at exposure: exposure -> the camera handed the pair over
            self.delivery_ms.append((rec.grab_done_t_ns - rec.left_t_ns) * 1e-6)
        found = LocatedMarkers.of(frame, rec.points_mm, rec.left_px, rec.right_px)
        return Prefetched(frame, found, None, rec.pair_seq)

    # ------------------------------------------------------------------ channel
    def _pump(self, timeout_s: float) -> Any:
        """Receive channel messages for up to ``timeout_s``; returns the first ready/failed."""
        try:
            if not self._conn.poll(timeout_s):
                return None
            msg = self._conn.recv()
        except (EOFError, OSError):
            if self._crash is None and not self._child.running:
                self._crash = self._child.exited()
            return None
        if msg[0] == "crashed":
            last = str(msg[1]).strip().splitlines()[-1:] or ["?"]
            self._crash = f"perception process crashed: {last[0]}"
        return msg

    def _wait_ready(self) -> Any:
        """The child's ``ready`` or ``failed`` answer (blocking, :data:`START_TIMEOUT_S` at most).

        Raises:
            DeviceTimeoutError: no answer in time. DisconnectedError: the child is gone first.
        """
        def receive(wait_s: float) -> Any:
            msg = self._pump(wait_s)
            return msg if msg is not None and msg[0] in ("ready", "failed") else None

        timed_out = f"perception process did not start within {START_TIMEOUT_S} s"
        return self._child.wait_message(receive, self._gone_now, START_TIMEOUT_S, timed_out, ALIVE_CHECK_S)
