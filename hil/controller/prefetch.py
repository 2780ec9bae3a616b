"""Frame prefetcher: grab the next stereo pair and locate its markers in a background thread, so the
control thread keeps streaming servo commands while a pair is exposed, transferred and processed.

Real time only (the controller uses it when its clock is the wall clock): with a manual clock a
second thread would make the simulated timeline depend on thread scheduling.

Thread contract:

- One *worker* thread (started by :meth:`FramePrefetcher.start`, a daemon named
  ``frame_prefetch``) is the only caller of ``camera.grab`` and of ``locate`` while the prefetcher
  runs. It loops: grab the next pair (blocking in the camera), run ``locate`` on it (pure CPU),
  put the result in a one-slot mailbox. The slot is *latest wins*: a result nobody took yet is
  replaced by the newer one and counted in :attr:`FramePrefetcher.overwritten`.
- One *consumer* (the control thread) calls :meth:`~FramePrefetcher.ready` (never blocks) and
  :meth:`~FramePrefetcher.take` (blocks until a result, an error, or the timeout).
- The worker never touches the robot, the safety layer or any controller state: it only reads
  the camera and computes marker centres.

Errors: any exception the camera's ``grab`` raises in the worker (a ``DriverError`` such as
``DeviceTimeoutError`` or ``DisconnectedError``, or anything unexpected) is handed to the
consumer, and :meth:`~FramePrefetcher.take` raises that same exception object (same type,
device and message) as a direct ``grab`` would have; the worker then waits until it was taken
before it grabs again (so a dead stream does not spin). An exception from ``locate`` travels with
its frame in :attr:`Prefetched.error`: the consumer raises it where it would have called
``locate`` itself. A :class:`~drivers.interfaces.errors.LifecycleError` raised after the camera was
closed (or after :meth:`~FramePrefetcher.stop`) ends the worker quietly: it is the end of the
stream, not a fault; the worker never calls ``grab`` on a camera that is not ACTIVE.

Shutdown: :meth:`~FramePrefetcher.stop` (idempotent) asks the worker to end and joins it; a grab
in progress finishes first (bounded by the grab timeout). Stop it before the camera is closed.

The GIL: both threads run Python and share one interpreter lock. A thread that wakes up for its
next servo deadline gets the lock only once the worker is asked to drop it, up to one switch
interval later (``sys.getswitchinterval()``, 5 ms by default: 2.5 periods at 500 Hz). For the
real-time run the controller lowers it to :data:`REALTIME_SWITCH_INTERVAL_S` with
:func:`realtime_switch_interval`. Measured with ``hil soak --rate 500`` (docs/benchmarks.md):
0.5 ms instead of 5 ms halved the longest servo gap (63-69 -> 24-33 ms) and the frame-boundary
misses (74-90 % -> 40-48 % of the frame boundaries); the missed-deadline fraction stayed within the
machine's noise (4-11 %). At 125 Hz it made no difference we could measure.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, LifecycleError
from drivers.interfaces.lifecycle import DeviceState
from hil.controller.located import LocatedMarkers, locate_in
from hil.log import get_logger

FloatArray = NDArray[np.float64]
_log = get_logger(__name__)

#: How often a waiting :meth:`FramePrefetcher.take` checks its ``wake`` condition, s.
WAKE_POLL_S = 0.001

#: GIL switch interval while the prefetcher runs in real time, s (see the module doc).
REALTIME_SWITCH_INTERVAL_S = 0.0005


@contextlib.contextmanager
def realtime_switch_interval(interval_s: float = REALTIME_SWITCH_INTERVAL_S) -> Iterator[None]:
    """Within the block, ``sys.setswitchinterval(interval_s)`` (never above the current value);
    the previous value is restored on exit. Process-wide, so used in one place: the controller's
    real-time run with the prefetcher."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(min(previous, interval_s))
    try:
        yield
    finally:
        sys.setswitchinterval(previous)


@dataclass(frozen=True)
class Prefetched:
    """One prefetched stereo pair.

    Attributes:
        frame: the pair as ``camera.grab`` returned it.
        located: what ``locate`` found in it (:func:`~hil.controller.located.locate_in`: the
            triangulated centres, optical frame, mm, and the per-camera centres, px, when the
            locator gives them); None when it raised.
        error: what ``locate`` raised (raise it where perception happens), else None.
        seq: 1, 2, ... in the order the worker produced the results.
    """

    frame: StereoFrame
    located: LocatedMarkers | None
    error: Exception | None
    seq: int

    @property
    def points_mm(self) -> FloatArray | None:
        """The triangulated marker centres (M, 3), optical frame, mm (read-only); None when
        ``locate`` raised."""
        return None if self.located is None else self.located.points_mm


class FramePrefetcher:
    """Background grab + perception with a one-slot, latest-wins mailbox (see the module doc).

    Args:
        camera: an ACTIVE stereo camera; only the worker calls its ``grab`` while running.
        locate: stereo pair -> marker centres (M, 3), optical frame, mm (pure; run in the worker).
        grab_timeout_s: the timeout the worker passes to ``grab``, s (> 0).

    Attributes:
        overwritten: results replaced before they were taken (latest wins).
        produced: results (pairs) the worker put in the mailbox.
    """

    def __init__(self, camera: StereoCamera, locate: Callable[[StereoFrame], FloatArray],
                 grab_timeout_s: float) -> None:
        if not grab_timeout_s > 0:
            raise ValueError(f"grab timeout must be > 0 s, got {grab_timeout_s}")
        self.camera = camera
        self.locate = locate
        self.grab_timeout_s = grab_timeout_s
        self.overwritten = 0
        self.produced = 0
        self._cond = threading.Condition()
        self._slot: Prefetched | BaseException | None = None
        self._stopping = False
        self._ended = False   # the worker left its loop (stopped, or the camera was closed)
        self._locating = False   # the worker has a pair and runs ``locate`` on it
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ consumer side
    def start(self) -> None:
        """Start the worker (once; a second call does nothing). Never blocks."""
        with self._cond:
            if self._thread is not None:
                return
            self._thread = threading.Thread(target=self._work, name="frame_prefetch", daemon=True)
            self._thread.start()

    @property
    def running(self) -> bool:
        """Whether the worker thread is alive."""
        t = self._thread
        return t is not None and t.is_alive()

    def ready(self) -> bool:
        """Whether :meth:`take` would return (or raise a device error) at once. Never blocks."""
        with self._cond:
            return self._slot is not None

    def take(self, timeout_s: float, wake: Callable[[], bool] | None = None) -> Prefetched | None:
        """The newest result, waiting up to ``timeout_s`` for a pair to *arrive* (blocking; the
        consumer thread): the grab's timeout semantics. A pair that arrived in time but is still in
        ``locate`` is waited for (``locate`` is bounded CPU work, as it is on the direct path).
        With ``wake``, it is checked every :data:`WAKE_POLL_S` while waiting: once it returns
        True (an operator input waits), ``take`` returns None at once, without a pair.

        Once the worker has ended (after :meth:`stop`, or the camera was closed) this is a direct
        ``camera.grab(timeout_s)`` plus ``locate``, so a closed camera raises its own
        LifecycleError here, as a direct grab would.

        Raises:
            DriverError (or whatever ``grab`` raised in the worker): that same exception object.
            DeviceTimeoutError: nothing arrived within ``timeout_s`` (names the camera).
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._slot is None and not self._ended:
                if wake is not None and wake():
                    return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(min(remaining, WAKE_POLL_S) if wake is not None else remaining)
            if self._slot is None and self._locating:
                self._cond.wait_for(lambda: self._slot is not None or self._ended)
            item, self._slot = self._slot, None
            self._cond.notify_all()   # a worker waiting for its error to be taken
        if isinstance(item, BaseException):
            raise item
        if item is not None:
            return item
        if self._ended:
            return self._direct(timeout_s)
        raise DeviceTimeoutError(self.camera.name, f"no stereo pair within {timeout_s} s")

    def wait_ended(self, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` until the worker has left its loop (after :meth:`stop`, or
        once it found the camera closed); returns whether it has."""
        with self._cond:
            return self._cond.wait_for(lambda: self._ended, timeout_s)

    def stop(self, timeout_s: float | None = None) -> None:
        """Ask the worker to end and join it (idempotent). Blocks until the grab in progress, if
        any, returns (at most the grab timeout plus ``locate``), or ``timeout_s`` when given; a
        worker still alive then is logged (``frame_prefetch_join_timeout``) and left as a daemon."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
            t = self._thread
        if t is None or t is threading.current_thread():
            with self._cond:
                self._ended = True
            return
        t.join(timeout_s if timeout_s is not None else self.grab_timeout_s + 5.0)
        if t.is_alive():
            _log.error("frame_prefetch_join_timeout", camera=self.camera.name)

    # ------------------------------------------------------------------ worker side
    def _direct(self, timeout_s: float) -> Prefetched:
        frame = self.camera.grab(timeout_s=timeout_s)
        found, err = self._locate(frame)
        self.produced += 1
        return Prefetched(frame, found, err, self.produced)

    def _locate(self, frame: StereoFrame) -> tuple[LocatedMarkers | None, Exception | None]:
        try:
            return locate_in(self.locate, frame), None
        except Exception as exc:  # noqa: BLE001 - raised by the consumer where it perceives
            return None, exc

    def _closed(self) -> bool:
        return self._stopping or self.camera.state is not DeviceState.ACTIVE

    def _work(self) -> None:
        try:
            while not self._closed():
                try:
                    frame = self.camera.grab(timeout_s=self.grab_timeout_s)
                except LifecycleError as exc:
                    if self._closed():
                        break   # closed under us: the end of the stream, not a fault
                    self._post_error(exc)
                    continue
                except Exception as exc:  # noqa: BLE001 - delivered to the consumer, raised there
                    if self._stopping:
                        break
                    self._post_error(exc)
                    continue
                if self._stopping:
                    break
                with self._cond:
                    self._locating = True
                found, err = self._locate(frame)
                self._post(frame, found, err)
        finally:
            with self._cond:
                self._ended = True
                self._locating = False
                self._cond.notify_all()

    def _post(self, frame: StereoFrame, found: LocatedMarkers | None, err: Exception | None) -> None:
        with self._cond:
            if isinstance(self._slot, Prefetched):
                self.overwritten += 1
            self.produced += 1
            self._slot = Prefetched(frame, found, err, self.produced)
            self._locating = False
            self._cond.notify_all()

    def _post_error(self, exc: BaseException) -> None:
        """Hand ``exc`` over (it replaces an untaken result) and wait until it was taken."""
        with self._cond:
            if isinstance(self._slot, Prefetched):
                self.overwritten += 1
            self._slot = exc
            self._cond.notify_all()
            self._cond.wait_for(lambda: self._slot is not exc or self._stopping)
