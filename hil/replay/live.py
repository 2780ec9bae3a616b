"""The live 3D view: a runtime plugin on the snapshot hooks that streams a run to Rerun
(``hil run --viewer FILE.rrd|ADDRESS``, ``hil console --viewer ...``), like the OpenIGTLink stream.

Contract: the hooks (called in the controller's thread) only append the frozen snapshot to a
bounded queue (a deque: no lock, no wake-up): they never block and never do I/O. A snapshot the
queue cannot take is dropped and counted (:attr:`LiveViewerPlugin.dropped`). One worker thread
(daemon, named ``hil-viewer``) wakes every ``poll_s`` (20 ms), takes the queued snapshots and
writes them through a :class:`SnapshotWriter` — by default
:class:`RerunSnapshotWriter` — so a slow viewer or disk only costs drops, never tick time.
:meth:`LiveViewerPlugin.close` (idempotent) stops the worker after it has written what is queued
(at most ``close_timeout_s``; the rest is abandoned and counted ``lost_on_close``), joins it and
closes the writer; call it on every path.

Memory is bounded on both sides of the worker, for a stream of any length:

- before it, the queue (``queue_size`` snapshots);
- after it, Rerun encodes and writes in threads of its own, through channels with no bound, so
  a worker that logs faster than Rerun writes (a busy machine, a slow disk or viewer) would pile
  up encoded data in the process (a writer logging flat out on a loaded machine reached +180
  MB). So every ``drain_every_s`` (0.2 s, Rerun's own batching period) the worker waits until
  what it has logged has reached the file or the socket (:meth:`SnapshotWriter.drain`, at most
  ``drain_timeout_s``): a slow sink then holds the worker, the queue fills, and what it cannot
  take is dropped and counted, never kept. A drain that times out is counted (``drain_errors``)
  and the stream goes on;
- a ``.rrd`` file is written without Rerun's footer. The footer's manifest lists every chunk, and
  Rerun keeps it in memory until the file is closed: ~1 kB per chunk, a chunk per entity per
  0.2 s, which grew an 8-minute soak's supervisor by 3.6 MB a minute (~200 MB an hour). Without
  it the file is still a valid recording that the viewer, ``rerun rrd verify`` and
  ``rerun.chunk.RrdReader(...).stream()`` read (the reader warns that it has no footer);
  ``rerun rrd optimize`` adds one afterwards for fast random access. ``hil replay`` files keep
  their footer (written at once, not streamed).

Entities (same paths as a replay, :mod:`hil.replay.scene`; the optical frame is ``world``):
``world/skin/seen``, ``world/flange/seen``, ``world/robot/tcp``, ``world/robot/guide`` is not
streamed (the snapshot carries the TCP, the rig's guide offset is not in it), ``world/robot``
(``T_robot_from_optical`` inverse, once known), ``series/gate/frame_deviation_mm``,
``series/following/guide_error_mm``, ``series/truth/position_error_mm`` (simulator),
``events/transitions`` (every applied transition), and in simulation, once
:meth:`LiveViewerPlugin.follow_truth` is given the truth meter's latest positions
(``hil.controller.metrics.TruthMeter.last_positions``), ``world/truth/skin``, ``world/truth/entry``,
``world/truth/target`` and ``world/truth/path`` as in a replay: the hook takes the latest positions
with the snapshot (one attribute read), the worker writes each new one once, at its own time.
Timelines: ``session_time`` (the snapshot's ``t_ns`` since the first one) and ``tick``
(snapshots written).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from hil.controller.cost import CostHistogram
from hil.errors import InputFileError
from hil.log import get_logger
from hil.replay.recording import APPLICATION_ID, TIMELINE_TIME, blueprint
from hil.replay.rerun_env import import_rerun
from hil.replay.scene import SceneItem, truth_items
from plugins.hookspecs import hookimpl

if TYPE_CHECKING:
    from hil.controller.fsm import FireResult
    from hil.controller.snapshot import ControllerSnapshot

_log = get_logger(__name__)

#: The plugin's name in the run's plugin manager.
PLUGIN_NAME = "rerun_viewer"
#: Timeline of the live stream counting snapshots written.
TIMELINE_TICK = "tick"
#: Log event when the stream is closed (with its counts).
EV_VIEWER_CLOSED = "viewer_stream_closed"
#: Log events when a write or a drain first fails (with the error).
EV_VIEWER_WRITE_FAILED = "viewer_write_failed"
EV_VIEWER_DRAIN_FAILED = "viewer_drain_failed"
#: Default queue length (snapshots): 1 s of ticks at 500 Hz.
DEFAULT_QUEUE = 500
#: How often the worker waits for Rerun to write what it logged, and for how long at most, s.
DRAIN_EVERY_S = 0.2
DRAIN_TIMEOUT_S = 5.0


class SnapshotWriter(Protocol):
    """Writes snapshots somewhere (called in the worker thread only)."""

    def write_tick(self, snap: ControllerSnapshot) -> None: ...

    def write_transition(self, text: str, snap: ControllerSnapshot) -> None: ...

    def write_truth(self, positions: Mapping[str, Any]) -> None:
        """The simulator's true positions (a ``truth_positions`` record's fields)."""
        ...

    def drain(self, timeout_s: float) -> None:
        """Block until what was written has reached the sink (at most ``timeout_s``; raises
        when that is not enough)."""
        ...

    def close(self) -> None: ...


#: Where the latest true positions are read (the truth meter's ``last_positions``), or None.
TruthSource = Callable[[], Mapping[str, Any] | None]


def is_address(target: str) -> bool:
    """A viewer address (``rerun://``, ``rerun+http://``, ``rerun+https://``) rather than a file."""
    return target.startswith(("rerun://", "rerun+http://", "rerun+https://"))


class RerunSnapshotWriter:
    """Streams snapshots into a Rerun recording: a ``.rrd`` file, or a viewer at an address.

    Raises:
        ViewerUnavailableError: rerun-sdk is missing.
    """

    def __init__(self, target: str, recording_id: str | None = None) -> None:
        self.rr = import_rerun()
        self.rec = self.rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        if is_address(target):
            self.rec.connect_grpc(target, default_blueprint=blueprint())
        else:   # no footer: its manifest of every chunk would grow with the stream (module doc)
            self.rec.save(target, default_blueprint=blueprint(), write_footer=False)
        self.rec.set_log_time_enabled(False)
        self._t0: int | None = None
        self._tick = 0
        self._robot_placed = False

    def _time(self, snap: ControllerSnapshot) -> None:
        self._t0 = snap.t_ns if self._t0 is None else self._t0
        self.rec.set_time(TIMELINE_TICK, sequence=self._tick)
        self.rec.set_time(TIMELINE_TIME, duration=np.timedelta64(snap.t_ns - self._t0, "ns"))

    def write_tick(self, snap: ControllerSnapshot) -> None:
        rr, rec = self.rr, self.rec
        self._tick += 1
        self._time(snap)
        if not self._robot_placed and snap.T_robot_from_optical is not None:
            T = snap.T_robot_from_optical.inverse()
            rec.log("world/robot", rr.Transform3D(translation=T.t, mat3x3=T.R), static=True)
            self._robot_placed = True
        for entity, pts in (("world/skin/seen", snap.live_mm), ("world/flange/seen", snap.flange_mm)):
            if pts is not None:
                seen = pts[np.all(np.isfinite(pts), axis=1)]
                if len(seen):
                    rec.log(entity, rr.Points3D(seen, radii=rr.Radius.ui_points(4.0)))
        robot = snap.robot_now or snap.robot
        if robot is not None:
            rec.log("world/robot/tcp", rr.Points3D(robot.T_robot_from_tcp.t.reshape(1, 3),
                                                   radii=rr.Radius.ui_points(4.0)))
        for entity, x in (("series/gate/frame_deviation_mm", snap.gate_deviation_mm),
                          ("series/following/guide_error_mm", snap.guide_error_mm),
                          ("series/truth/position_error_mm", snap.truth_error_mm)):
            if x is not None and np.isfinite(x):
                rec.log(entity, rr.Scalars(float(x)))

    def write_transition(self, text: str, snap: ControllerSnapshot) -> None:
        self._time(snap)
        self.rec.log("events/transitions", self.rr.TextLog(text, level="INFO"))

    def write_truth(self, positions: Mapping[str, Any]) -> None:
        """``world/truth/*`` at the positions' own time (``truth_t_ns``); nothing before the
        first snapshot (no time origin yet)."""
        t_ns = positions.get("truth_t_ns")
        if self._t0 is None or not isinstance(t_ns, int):
            return
        self.rec.set_time(TIMELINE_TICK, sequence=self._tick)
        self.rec.set_time(TIMELINE_TIME, duration=np.timedelta64(t_ns - self._t0, "ns"))
        for item in truth_items(positions, self._tick, t_ns - self._t0):
            self._log_item(item)

    def _log_item(self, item: SceneItem) -> None:
        rr = self.rr
        if item.kind == "points":
            self.rec.log(item.entity, rr.Points3D(item.points, radii=rr.Radius.ui_points(4.0)))
        elif item.kind == "strips":
            self.rec.log(item.entity, rr.LineStrips3D([item.points]))

    def drain(self, timeout_s: float) -> None:
        """Rerun's blocking flush: the batcher's pending rows encoded and handed to the file or
        the socket (raises when ``timeout_s`` is not enough)."""
        self.rec.flush(timeout_sec=timeout_s)

    def close(self) -> None:
        try:
            self.rec.flush()
        finally:
            self.rec.disconnect()


@dataclass
class _Item:
    snap: ControllerSnapshot
    transition: str | None = None
    truth: Mapping[str, Any] | None = None


class LiveViewerPlugin:
    """The live stream (module doc). ``writer``: where snapshots go (started here: the worker
    thread starts in the constructor). ``hook_cost``: the time each hook call took, for the cost
    figure (a fixed histogram: every call counted, no growth)."""

    def __init__(self, writer: SnapshotWriter, queue_size: int = DEFAULT_QUEUE,
                 close_timeout_s: float = 5.0, poll_s: float = 0.02,
                 drain_every_s: float = DRAIN_EVERY_S, drain_timeout_s: float = DRAIN_TIMEOUT_S) -> None:
        self.writer = writer
        self.close_timeout_s = close_timeout_s
        self.drain_every_s = drain_every_s
        self.drain_timeout_s = drain_timeout_s
        self._q: collections.deque[_Item] = collections.deque()
        self._queue_size = queue_size
        self.poll_s = poll_s
        self._stop = threading.Event()
        self._abandon = threading.Event()
        self.offered = 0
        self.dropped = 0
        self.written = 0
        self.write_errors = 0
        self.drains = 0
        self.drain_errors = 0
        self.hook_cost = CostHistogram()
        self._truth: TruthSource | None = None
        self._truth_t_ns: object = None   # the worker's: the last positions written
        self.truth_written = 0
        self._closed = False
        self._thread = threading.Thread(target=self._work, name="hil-viewer", daemon=True)
        self._thread.start()

    def follow_truth(self, source: TruthSource | None) -> None:
        """Stream the simulator's true positions: ``source`` returns the latest (a mapping with
        ``truth_t_ns``, never mutated after it is returned) or None; called in the hook, so it
        must be an attribute read, e.g. ``lambda: meter.last_positions``. None: stop."""
        self._truth = source

    # ---------------------------------------------------------------- controller thread
    def _offer(self, item: _Item) -> None:
        t = time.perf_counter_ns()
        self.offered += 1
        if len(self._q) < self._queue_size:
            self._q.append(item)  # atomic; no lock, no wake-up of the worker (it polls)
        else:
            self.dropped += 1
        self.hook_cost.add_ns(time.perf_counter_ns() - t)

    @hookimpl
    def hil_on_tick(self, snapshot: ControllerSnapshot) -> None:
        source = self._truth
        self._offer(_Item(snapshot, truth=None if source is None else source()))

    @hookimpl
    def hil_on_transition(self, transition: FireResult, snapshot: ControllerSnapshot) -> None:
        text = (f"{transition.source.value} -> {transition.target.value} "
                f"({transition.transition_name}: {transition.reason})")
        self._offer(_Item(snapshot, text))

    # ---------------------------------------------------------------- worker thread
    def _work(self) -> None:
        """Every ``poll_s``: write what is queued, drain the writer every ``drain_every_s``
        (module doc); after :meth:`close` asks, end once the queue is empty."""
        last_drain = time.monotonic()
        while True:
            stopping = self._stop.wait(self.poll_s)
            while self._q and not self._abandon.is_set():
                self._write(self._q.popleft())
                if time.monotonic() - last_drain >= self.drain_every_s:
                    self._drain()
                    last_drain = time.monotonic()
            if stopping or self._abandon.is_set():
                return

    def _write(self, item: _Item) -> None:
        try:
            if item.transition is None:
                self.writer.write_tick(item.snap)
                self._write_truth(item.truth)
            else:
                self.writer.write_transition(item.transition, item.snap)
            self.written += 1
        except Exception as exc:  # noqa: BLE001 -- a viewer problem must not end the stream
            self.write_errors += 1
            if self.write_errors == 1:
                _log.warning(EV_VIEWER_WRITE_FAILED, error=repr(exc))

    def _drain(self) -> None:
        try:
            self.writer.drain(self.drain_timeout_s)
            self.drains += 1
        except Exception as exc:  # noqa: BLE001 -- a slow viewer must not end the stream
            self.drain_errors += 1
            if self.drain_errors == 1:
                _log.warning(EV_VIEWER_DRAIN_FAILED, error=repr(exc), timeout_s=self.drain_timeout_s)

    def _write_truth(self, truth: Mapping[str, Any] | None) -> None:
        """Each new set of true positions once (the worker thread)."""
        if truth is None or truth.get("truth_t_ns") == self._truth_t_ns:
            return
        self._truth_t_ns = truth.get("truth_t_ns")
        self.writer.write_truth(truth)
        self.truth_written += 1

    def counts(self) -> dict[str, int]:
        """``offered``, ``written``, ``dropped`` (queue full), ``write_errors``, ``lost_on_close``,
        ``drains`` and ``drain_errors`` (module doc)."""
        return {"offered": self.offered, "written": self.written, "dropped": self.dropped,
                "write_errors": self.write_errors,
                "lost_on_close": self.offered - self.dropped - self.written - self.write_errors,
                "drains": self.drains, "drain_errors": self.drain_errors}

    def close(self) -> dict[str, int]:
        """Write what is queued (at most ``close_timeout_s``), stop and join the worker, close
        the writer; the counts. Idempotent."""
        if not self._closed:
            self._closed = True
            self._stop.set()
            self._thread.join(self.close_timeout_s)
            if self._thread.is_alive():  # the writer is slow: abandon the rest of the queue
                self._abandon.set()
                self._thread.join()
            self.writer.close()
            _log.info(EV_VIEWER_CLOSED, **self.counts())
        return self.counts()


def open_live_viewer(target: str, recording_id: str | None = None,
                     writer_factory: Callable[[str, str | None], SnapshotWriter] | None = None,
                     ) -> LiveViewerPlugin:
    """The live plugin streaming to ``target`` (a ``.rrd`` path or a viewer address); its worker
    thread runs: close it on every path.

    Raises:
        InputFileError: ``target`` is a file whose directory does not exist.
        ViewerUnavailableError: rerun-sdk is missing.
    """
    check_target(target)
    make: Callable[[str, str | None], Any] = writer_factory or RerunSnapshotWriter
    return LiveViewerPlugin(make(target, recording_id))


def check_target(target: str) -> None:
    """Raises InputFileError when ``target`` is a file whose directory does not exist."""
    if not is_address(target) and not Path(target).resolve().parent.is_dir():
        raise InputFileError(target, "--viewer: the recording's directory does not exist")


def stream_line(plugin: LiveViewerPlugin, target: str) -> str:
    """One line saying what the stream did (counts and the hook's p99), for stderr."""
    c, cost = plugin.counts(), hook_cost_us(plugin)
    return (f"viewer stream {target}: {c['written']} of {c['offered']} snapshots written, "
            f"{c['dropped']} dropped; hook p99 {cost['p99']:.1f} us")


def hook_cost_us(plugin: LiveViewerPlugin) -> dict[str, float]:
    """p50 / p99 / max of the hook's time per call, microseconds (0 when never called); the
    percentiles are the upper edges of their 1 µs bins (:class:`hil.controller.cost.CostHistogram`)."""
    fig = plugin.hook_cost.figures()
    return {"p50": fig.p50_us or 0.0, "p99": fig.p99_us or 0.0, "max": fig.max_us or 0.0}
