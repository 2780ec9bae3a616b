"""The camera side of a tick: priming the pipeline, the real-time prefetcher, and reading the
devices (the stereo pair, the robot state, the tracker's latest samples) into the estimate.

Where pairs come from: a camera whose :attr:`~drivers.interfaces.camera.StereoCamera.perception_feed`
is set (the perception process's camera, :class:`hil.perception.camera.PerceptionCamera`, or a
wrapper of it) is never grabbed here: its feed has the pairs, already located, and stands in for
the prefetcher; otherwise the camera itself, through the prefetcher thread on the wall clock.

Blocking: the supervisor ticks on its own clock. :meth:`DevicePipeline.read` waits for the next pair
at most one *supervisor period* (``[procedure] supervisor_period_ms``; default 1.25 frame periods,
so while pairs arrive it ticks with each pair); when none arrived by then it still reads the robot
and the tracker and feeds their watchdogs, and the tick goes on without a pair (supervision only:
:attr:`DevicePipeline.pair_arrived` is False). Only when no pair arrived for the whole grab timeout
(:meth:`DevicePipeline.grab_timeout_s`, counted from the first wait after the last pair) does it
raise the camera's DeviceTimeoutError. This holds where the wait is on a prefetcher, a perception feed or the
simulated clock; a direct grab on the wall clock (``camera_prefetch = false``) blocks for the
whole grab timeout, as a real camera driver may count a short timeout as a lost frame.
On a pair the controller may have the tracker read after the pair's setpoint is out
(:meth:`DevicePipeline.read` with ``defer_tracker``, then :meth:`DevicePipeline.read_tracker`).
Errors: the devices' DriverError (a DeviceTimeoutError naming the camera when no pair arrives).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import TypeAlias

import numpy as np

from drivers.interfaces.camera import PairFeed as CameraPairFeed
from drivers.interfaces.camera import StereoCamera, StereoFrame
from drivers.interfaces.errors import DeviceTimeoutError, DriverError
from drivers.interfaces.robot import Robot, RobotState
from drivers.interfaces.tracker import PoseTracker
from hil.clock import Clock, MonotonicClock
from hil.controller import events as ev
from hil.controller.estimate import Estimate, FloatArray
from hil.controller.located import LocatedMarkers, locate_in
from hil.controller.metrics import RunMetrics
from hil.controller.prefetch import FramePrefetcher, Prefetched, realtime_switch_interval
from hil.log import get_logger
from hil.safety.watchdog import WatchdogSet
from hil.session.log import SessionLog

_log = get_logger(__name__)

#: Stereo frame -> triangulated marker centres (M, 3), optical frame, mm (any order).
MarkerLocator = Callable[[StereoFrame], FloatArray]

#: The default supervisor period in camera frame periods: long enough that a tick never ends
#: without the pair while pairs arrive on time, short enough that a camera gap is supervised.
SUPERVISOR_PERIOD_FRAMES = 1.25


#: Located pairs from elsewhere (the perception process), as the camera interface declares them
#: (:attr:`~drivers.interfaces.camera.StereoCamera.perception_feed`): the prefetcher's contract.
PairFeed: TypeAlias = CameraPairFeed[Prefetched]


def camera_silence_s(frame_period_s: float, configured_s: float | None = None) -> float:
    """How long no stereo pair may arrive before the camera is lost, s: ``configured_s``
    (``[safety] camera_silence_ms``) when set, else 4 frame periods and at least 0.2 s."""
    if configured_s is not None:
        return configured_s
    return max(4 * frame_period_s, 0.2)


class DevicePipeline:
    """Reads the devices for the controller (module doc). ``locate``: stereo pair -> marker
    centres (optical frame, mm)."""

    def __init__(self, camera: StereoCamera, robot: Robot, tracker: PoseTracker | None, clock: Clock,
                 locate: MarkerLocator, watchdogs: WatchdogSet, session: SessionLog,
                 metrics: RunMetrics, supervisor_period_s: float | None = None,
                 camera_silence_s: float | None = None) -> None:
        self.camera, self.robot, self.tracker, self.clock = camera, robot, tracker, clock
        self.locate = locate
        self.watchdogs, self.session, self.metrics = watchdogs, session, metrics
        self.frame_period_s = 1.0 / camera.frame_rate_hz
        #: ``[safety] camera_silence_ms`` in s (None: the default, :meth:`grab_timeout_s`)
        self.camera_silence_s = camera_silence_s
        #: the longest a tick waits for a pair before it supervises without one, s (module doc)
        self.supervisor_period_s = (SUPERVISOR_PERIOD_FRAMES * self.frame_period_s
                                    if supervisor_period_s is None else supervisor_period_s)
        #: whether the latest :meth:`read` brought a new pair (False: a tick without one)
        self.pair_arrived = False
        #: whether the latest :meth:`read` left the tracker for :meth:`read_tracker`
        self.tracker_deferred = False
        #: the clock when the first read waiting for the next pair began (None: not waiting); the
        #: grab timeout counts from there, as it counted from one blocking grab before
        self._waiting_since_ns: int | None = None
        self.primed = False   # the camera pipeline's first (late) pair has been consumed
        self.feed: PairFeed | None = camera.perception_feed   # the perception process's pairs (module doc)
        self.prefetch: FramePrefetcher | PairFeed | None = None
        self.prefetched: Prefetched | None = None   # the result the current tick perceives
        #: the markers located in the latest pair perceived (None before one, or when locating it
        #: raised): what snapshots show per camera
        self.last_located: LocatedMarkers | None = None

    def grab_timeout_s(self) -> float:
        """How long no pair may arrive before the camera is lost, s (:func:`camera_silence_s`)."""
        return camera_silence_s(self.frame_period_s, self.camera_silence_s)

    def prime(self, timeout_s: float = 2.0) -> None:
        """Grab and discard one stereo pair, once, before the first tick judges any.

        A camera's first buffer or a simulator's first render is late (caches, buffers): it is
        consumed here, so the first pair the controller judges is a fresh one and the watchdogs
        stay strict for every pair. Logs ``pipeline_primed`` (the discarded pair's age) or
        ``pipeline_prime_failed`` (then the camera watchdog reports the missing data). Blocks up to
        ``timeout_s`` plus the grab's own work; never raises for a device error.
        """
        if self.primed:
            return
        self.primed = True
        t_ns = self.clock.now_ns()
        try:
            frame = self._grab_next(max(timeout_s, 4 * self.frame_period_s))
        except DriverError as exc:
            self.session.write(ev.PIPELINE_PRIME_FAILED, reason=str(exc))
            _log.warning(ev.PIPELINE_PRIME_FAILED, reason=str(exc))
            return
        now = self.clock.now_ns()
        self.session.write(ev.PIPELINE_PRIMED, frame_seq=frame.left.seq,
                           first_frame_age_s=(now - frame.left.t_ns) * 1e-9, took_s=(now - t_ns) * 1e-9)

    @contextlib.contextmanager
    def prefetching(self, enabled: bool) -> Iterator[None]:
        """On the wall clock (MonotonicClock) with ``enabled`` (``procedure.camera_prefetch``):
        grab and locate the next pair in a :class:`~hil.controller.prefetch.FramePrefetcher` thread
        (so COMPENSATE keeps streaming meanwhile) with the GIL switch interval lowered; otherwise
        (a manual clock: a deterministic simulation) nothing changes. The worker is stopped and
        joined when the block ends, however it ends, before the caller can close the camera;
        ``frame_prefetch_stopped`` records its counts. With a perception feed (module doc) the feed
        is the prefetcher, enabled or not: nothing starts or stops here."""
        if self.feed is not None:
            yield from self._feeding(self.feed)
            return
        if not (enabled and isinstance(self.clock, MonotonicClock)):
            yield
            return
        pf = FramePrefetcher(self.camera, self.locate, self.grab_timeout_s())
        self.prefetch = pf
        try:
            with realtime_switch_interval():
                pf.start()
                yield
        finally:
            self.prefetch = None
            self.prefetched = None
            pf.stop()
            self.metrics.frames_overwritten += pf.overwritten
            self.session.write(ev.FRAME_PREFETCH_STOPPED, pairs=pf.produced, overwritten=pf.overwritten)

    def _feeding(self, feed: PairFeed) -> Iterator[None]:
        produced, overwritten = feed.produced, feed.overwritten
        self.prefetch = feed
        try:
            yield
        finally:
            self.prefetch = None
            self.prefetched = None
            skipped = feed.overwritten - overwritten
            self.metrics.frames_overwritten += skipped
            self.session.write(ev.FRAME_PREFETCH_STOPPED, pairs=feed.produced - produced, overwritten=skipped,
                               process=True)

    def _grab_next(self, timeout_s: float) -> StereoFrame:
        """The next pair: from the camera, or the first the perception feed publishes from now on
        (what it published before, while the supervisor was starting, is skipped: it is as late
        as a camera's first buffer)."""
        if self.feed is not None:
            if self.feed.ready():
                self.feed.take(0.0)
            got = self.feed.take(timeout_s)
            assert got is not None   # no wake: a pair or an error
            return got.frame
        return self.camera.grab(timeout_s=timeout_s)

    def read(self, est: Estimate, wake: Callable[[], bool] | None = None,
             defer_tracker: bool = False) -> RobotState | None:
        """The next pair (if one arrives within the supervisor period), the robot state and the
        tracker samples into ``est`` (module doc); feeds the watchdogs and sets
        :attr:`pair_arrived`. Returns the robot state, or None when ``wake`` (an operator input
        waits) ended the wait for the pair first (real time; nothing read).

        ``defer_tracker``: when a pair arrived, leave the tracker for :meth:`read_tracker` (the
        controller reads it once the pair's setpoint is out, when no tracker sample feeds that
        setpoint); :attr:`tracker_deferred` says whether it was left.

        Raises:
            DeviceTimeoutError: no pair for the whole grab timeout since the last one (the camera's).
            DriverError: a device's error (the camera's at once, the robot's, the tracker's).
        """
        self.prefetched = None
        self.pair_arrived = False
        self.tracker_deferred = False
        frame, woken = self._next_pair(wake)
        if woken:
            return None
        now = self.clock.now_ns()
        if frame is not None:
            self.pair_arrived = True
            self.metrics.frames += 1
            est.last_frame = frame
            self.watchdogs["camera"].feed(frame.left.t_ns, now)
        st = self.robot.state_now()
        est.record_robot_state(st)
        self.watchdogs["robot"].feed(st.t_ns, now)
        self.tracker_deferred = defer_tracker and frame is not None and self.tracker is not None
        if not self.tracker_deferred:
            self.read_tracker(est)
        return st

    def read_tracker(self, est: Estimate) -> None:
        """The tracker's latest samples into ``est`` (nothing without a tracker); feeds its
        watchdog with the newest fresh one. Raises the tracker's DriverError."""
        self.tracker_deferred = False
        if self.tracker is None:
            return
        samples = self.tracker.latest()
        est.record_tracker_samples(samples)
        fresh = [s.t_ns for s in samples.values() if not s.missing]
        if fresh:
            self.watchdogs["tracker"].feed(max(fresh), self.clock.now_ns())

    def _next_pair(self, wake: Callable[[], bool] | None) -> tuple[StereoFrame | None, bool]:
        """Wait up to the supervisor period (or what is left of the grab timeout) for a pair:
        (the pair or None when none arrived yet (module doc), whether ``wake`` ended the wait)."""
        source = self.prefetch if self.prefetch is not None else self.feed
        sliced = source is not None or not isinstance(self.clock, MonotonicClock)
        timeout_s = self.grab_timeout_s()
        start_ns = self.clock.now_ns()
        if self._waiting_since_ns is None:
            self._waiting_since_ns = start_ns
        left_s = timeout_s - (start_ns - self._waiting_since_ns) * 1e-9
        wait_s = min(self.supervisor_period_s, left_s) if sliced else timeout_s
        last = not sliced or wait_s >= left_s
        try:
            if source is not None:
                got = source.take(max(wait_s, 0.0), wake)
                if got is None:
                    return None, True
                self.prefetched, frame = got, got.frame
            else:
                frame = self.camera.grab(timeout_s=max(wait_s, 0.0))
        except DeviceTimeoutError as exc:
            if not last:
                return None, False   # no pair yet: a tick without one
            self._waiting_since_ns = None
            if sliced:
                raise DeviceTimeoutError(exc.device, f"no stereo pair within {timeout_s:g} s") from exc
            raise
        except DriverError:
            self._waiting_since_ns = None   # the next wait has the whole grab timeout again
            raise
        self._waiting_since_ns = None
        return frame, False

    def located(self, frame: StereoFrame) -> FloatArray:
        """The marker centres of ``frame`` (M, 3), optical frame, mm (a fresh array): the
        prefetcher's (or the error ``locate`` raised on it, raised here), else located now. The
        whole result, per camera too, is kept in :attr:`last_located`."""
        self.last_located = None
        got = self.prefetched
        if got is not None and got.frame is frame:
            if got.error is not None:
                raise got.error
            found = got.located if got.located is not None else LocatedMarkers.of(frame, np.zeros((0, 3)))
        else:
            found = locate_in(self.locate, frame)
        self.last_located = found
        return np.array(found.points_mm, dtype=np.float64)

    def next_pair_ready(self) -> bool | None:
        """None without a prefetcher, else whether it has the next pair (or error) ready."""
        pf = self.prefetch
        return None if pf is None else pf.ready()
