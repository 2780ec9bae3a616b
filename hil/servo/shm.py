"""Shared memory between the supervisor and the servo loop: the setpoint block (supervisor ->
servo), the state ring and the loop statistics (servo -> everyone).

One writer per region, any number of readers, no locks:

- :class:`SetpointBlock` is a *seqlock*: the writer makes the sequence word odd, writes the
  fields, makes it even again; a reader copies the fields between two reads of the sequence word
  and retries when the word was odd or changed, for at most 50 µs (then it keeps its last copy:
  the real-time loop never waits for a preempted writer). A reader never sees half a setpoint.
- :class:`StateRing` is a ring of per-period records (robot state, what was commanded). The
  writer fills slot ``head % N`` and then increments ``head``; a reader copies slot ``head - 1``
  and accepts it when ``head`` did not move by ``N - 1`` or more meanwhile (the slot was not
  overwritten under it).
- :class:`LoopStats` are counters and histograms only the servo loop writes.

Ordering: the fields are plain 8-byte words (numpy views over one buffer). On x86-64 (total store
order, the machines this runs on) stores become visible in program order and loads are not
reordered with older loads, which is what the seqlock needs; a port to a weakly ordered CPU needs
explicit fences here.

Buffers: :meth:`ShmRegion.create` makes a named ``multiprocessing.shared_memory`` segment (the
servo process attaches it by name); :meth:`ShmRegion.local` makes a plain in-process buffer of the
same layout (the in-process loop of a simulated run). Nothing here allocates on the read and write
paths except the caller-provided output arrays' first creation. Closing a region never unmaps
memory a view still reads (:meth:`ShmRegion.close`): a reader in another thread may hold one while
:meth:`hil.servo.process.ServoProcess.restart` frees the old regions.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import time
from dataclasses import dataclass, field
from enum import IntEnum
from multiprocessing import shared_memory
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

WORD = 8


class ServoMode(IntEnum):
    """What the supervisor asks of the servo loop."""

    IDLE = 0    # no servo command (the arm holds, or runs a move started by a command)
    TRACK = 1   # follow the setpoint (extrapolated, rate- and acceleration-limited)
    STOP = 2    # stop the arm on the next period, retry until delivered, keep reading it
    HOLD = 3    # come to rest from the current command at the acceleration limit and hold the
    #             pose there, commanding it every period (the arm stays under servo control and
    #             following supervision; the tracking session goes on)
    MOVE = 4    # a straight-line move to the setpoint pose from the actual pose at rest
    #             (hil.servo.trajectory: a trapezoidal profile streamed every period, checked and
    #             supervised like tracking), then hold the target; each move is its own session


class ShmRegion:
    """A zero-initialised buffer of ``words`` 8-byte words with int64 and float64 views.

    Use :meth:`create` (owner), :meth:`attach` (another process) or :meth:`local`.
    """

    def __init__(self, buf: Any, words: int, shm: shared_memory.SharedMemory | None, owner: bool) -> None:
        self.words = words
        self._shm = shm
        self._owner = owner
        self._mmap: mmap.mmap | None = None
        # np.frombuffer keeps the buffer exported for as long as any view of it lives, so closing
        # the segment cannot unmap memory a view (a LoopStats, a ring reader in another thread)
        # still reads: the mapping goes with the last view (see close)
        self.i: IntArray = np.frombuffer(buf, dtype=np.int64, count=words)
        self.f: FloatArray = np.frombuffer(buf, dtype=np.float64, count=words)

    @classmethod
    def create(cls, words: int) -> ShmRegion:
        shm = shared_memory.SharedMemory(create=True, size=words * WORD)
        region = cls(shm.buf, words, shm, owner=True)
        region.i[:] = 0
        return region

    @classmethod
    def attach(cls, name: str, words: int) -> ShmRegion:
        """Map the segment ``name`` another process created (POSIX shared memory under /dev/shm,
        mapped directly: no resource tracker in this process, which would unlink the segment when
        this process exits)."""
        fd = os.open(os.path.join("/dev/shm", name.lstrip("/")), os.O_RDWR)
        try:
            mm = mmap.mmap(fd, words * WORD)
        finally:
            os.close(fd)
        region = cls(mm, words, None, owner=False)
        region._mmap = mm
        return region

    @classmethod
    def local(cls, words: int) -> ShmRegion:
        return cls(bytearray(words * WORD), words, None, owner=False)

    @property
    def name(self) -> str | None:
        """The shared segment's name (None for a local buffer)."""
        return None if self._shm is None else self._shm.name

    def close(self) -> None:
        """Release the views and the segment (the owner also unlinks its name). Idempotent.

        Views other objects still hold (another thread may be reading them) keep the mapping
        alive: it is unmapped with the last of them, never under them. A created segment whose
        mapping is still in use is kept in :data:`_LINGERING` (its ``SharedMemory`` object must
        not be collected first) and closed by a later :meth:`close` once free."""
        shm, self._shm = self._shm, None
        mm, self._mmap = self._mmap, None
        self.i = np.zeros(0, dtype=np.int64)
        self.f = np.zeros(0, dtype=np.float64)
        if mm is not None:   # attached: the views' memoryviews hold the mmap; it goes with them
            with contextlib.suppress(BufferError):
                mm.close()
        _close_lingering()
        if shm is not None:
            close_segment(shm)
            if self._owner:
                shm.unlink()


#: created segments closed while views of them were still alive (:func:`close_segment`)
_LINGERING: list[shared_memory.SharedMemory] = []


def close_segment(shm: shared_memory.SharedMemory) -> None:
    """Close ``shm``'s mapping (not its name) unless ``np.frombuffer`` views of it are still
    alive: then it lingers in :data:`_LINGERING` (its ``SharedMemory`` object must outlive the
    views, or its finaliser would fail on the export) and a later call closes it once free, so
    memory is never unmapped under a reader. Lingering segments already free are closed first."""
    _close_lingering()
    try:
        shm.close()
    except BufferError:
        _LINGERING.append(shm)


def _close_lingering() -> None:
    """Close the lingering segments whose views are all gone."""
    for shm in list(_LINGERING):
        try:
            shm.close()
        except BufferError:
            continue
        _LINGERING.remove(shm)


# ---------------------------------------------------------------------------- setpoint block
# word offsets
_SEQ, _MODE, _TRACK_ID, _T_REF, _VALID_UNTIL, _EXPOSURE, _STOP_ID, _FRAME_SEQ = range(8)
_POSE = 8          # 12 words: R (row-major 9), t (3)
_VEL = 20          # 6 words: v (mm/s, robot frame), w (rad/s, robot frame)
_SCALE, _HORIZON, _LEAD = 26, 27, 28
_MOVE_SPEED, _MOVE_ACCEL = 29, 30
SETPOINT_WORDS = 32
#: how long a reader retries while a write is in progress, ns: a running writer finishes a write
#: in ~10 µs; longer means it was preempted mid-write (see :meth:`SetpointBlock.read`)
READ_MAX_WAIT_NS = 50_000


@dataclass
class Setpoint:
    """A copy of the setpoint block (one reader's reusable buffer).

    Attributes:
        seq: the block's sequence number when copied (even; grows with every write).
        mode: :class:`ServoMode`.
        track_id: grows when a new tracking session starts (the loop then restarts its rate limiter
            from the arm's actual pose at rest).
        t_ref_ns: the time the pose is valid at (the stereo pair's exposure), controller clock.
        valid_until_ns: after this the setpoint is stale (the loop ramps down to hold).
        exposure_t_ns: the exposure the setpoint was computed from (for the latency figure).
        stop_id: grows with every stop request (the loop acknowledges each in the stats).
        frame_seq: the stereo pair's sequence number.
        R, t_mm: the target TCP pose ``T_robot_from_tcp`` at ``t_ref_ns`` (mm).
        v_mm_s, w_rad_s: its linear and angular velocity (robot frame).
        speed_scale: (0, 1]: scales the speed limit (resume ramp).
        max_horizon_s: the loop never extrapolates further than this past ``t_ref_ns``.
        lead_s: the arm's actuation lag added to the extrapolation.
        move_speed_mm_s, move_accel_mm_s2: a MOVE's TCP speed and acceleration (the pose is its
            target; ``track_id`` its session).
    """

    seq: int = 0
    mode: int = ServoMode.IDLE
    track_id: int = 0
    t_ref_ns: int = 0
    valid_until_ns: int = 0
    exposure_t_ns: int = 0
    stop_id: int = 0
    frame_seq: int = 0
    R: FloatArray = field(default_factory=lambda: np.eye(3))
    t_mm: FloatArray = field(default_factory=lambda: np.zeros(3))
    v_mm_s: FloatArray = field(default_factory=lambda: np.zeros(3))
    w_rad_s: FloatArray = field(default_factory=lambda: np.zeros(3))
    speed_scale: float = 1.0
    max_horizon_s: float = 0.0
    lead_s: float = 0.0
    move_speed_mm_s: float = 0.0
    move_accel_mm_s2: float = 0.0


class SetpointBlock:
    """The supervisor's setpoint for the servo loop (seqlock, module doc). One writer."""

    def __init__(self, region: ShmRegion) -> None:
        if region.words < SETPOINT_WORDS:
            raise ValueError(f"setpoint block needs {SETPOINT_WORDS} words, region has {region.words}")
        self.region = region
        self._pose = np.zeros(12)
        self._vel = np.zeros(6)

    # ------------------------------------------------------------------ writer
    def _begin(self) -> None:
        self.region.i[_SEQ] += 1   # odd: a write is in progress

    def _end(self) -> None:
        self.region.i[_SEQ] += 1   # even: consistent

    def write_track(self, *, track_id: int, R: FloatArray, t_mm: FloatArray, v_mm_s: FloatArray,
                    w_rad_s: FloatArray, t_ref_ns: int, valid_until_ns: int, exposure_t_ns: int,
                    frame_seq: int, speed_scale: float, max_horizon_s: float, lead_s: float) -> None:
        """Publish a tracking setpoint (see :class:`Setpoint` for the fields)."""
        i, f = self.region.i, self.region.f
        self._begin()
        i[_MODE] = ServoMode.TRACK
        i[_TRACK_ID] = track_id
        i[_T_REF] = t_ref_ns
        i[_VALID_UNTIL] = valid_until_ns
        i[_EXPOSURE] = exposure_t_ns
        i[_FRAME_SEQ] = frame_seq
        f[_POSE:_POSE + 9] = np.asarray(R, dtype=np.float64).reshape(9)
        f[_POSE + 9:_POSE + 12] = t_mm
        f[_VEL:_VEL + 3] = v_mm_s
        f[_VEL + 3:_VEL + 6] = w_rad_s
        f[_SCALE] = speed_scale
        f[_HORIZON] = max_horizon_s
        f[_LEAD] = lead_s
        self._end()

    def write_move(self, *, track_id: int, R: FloatArray, t_mm: FloatArray, speed_mm_s: float,
                   accel_mm_s2: float) -> None:
        """Start a straight-line MOVE to ``(R, t_mm)`` in the new session ``track_id`` (see
        :class:`Setpoint`)."""
        i, f = self.region.i, self.region.f
        self._begin()
        i[_MODE] = ServoMode.MOVE
        i[_TRACK_ID] = track_id
        f[_POSE:_POSE + 9] = np.asarray(R, dtype=np.float64).reshape(9)
        f[_POSE + 9:_POSE + 12] = t_mm
        f[_VEL:_VEL + 6] = 0.0
        f[_SCALE] = 1.0   # a HOLD in the move's session decelerates at the full limits
        f[_MOVE_SPEED] = speed_mm_s
        f[_MOVE_ACCEL] = accel_mm_s2
        self._end()

    def write_hold(self, track_id: int) -> None:
        """Switch to HOLD in tracking session ``track_id`` (the current one: the loop holds from
        its last command; a new one: the loop starts it from the actual pose, at rest)."""
        i = self.region.i
        self._begin()
        i[_MODE] = ServoMode.HOLD
        i[_TRACK_ID] = track_id
        self._end()

    def write_mode(self, mode: ServoMode) -> int:
        """Switch to IDLE or STOP (a STOP gets a new stop id, returned; else the current one)."""
        i = self.region.i
        self._begin()
        i[_MODE] = mode
        if mode is ServoMode.STOP:
            i[_STOP_ID] += 1
        stop_id = int(i[_STOP_ID])
        self._end()
        return stop_id

    # ------------------------------------------------------------------ reader
    def read(self, out: Setpoint, max_wait_ns: int = READ_MAX_WAIT_NS) -> Setpoint | None:
        """Copy the block into ``out`` and return it; retried while a write is in progress, for at
        most ``max_wait_ns``. Then None, and ``out`` is left as it was: the writer (the supervisor,
        a normal-priority process whose thread can also lose its interpreter lock mid-write) can
        be preempted in the middle of a write for milliseconds, and a real-time reader spinning
        until it runs again would miss its periods at 100 % CPU — priority inversion. The caller
        goes on with its last copy for this period and reads again the next; a copy that stays
        old goes stale by its ``valid_until_ns``. Never a torn copy: fields land in ``out`` only
        after a consistent read.
        """
        i, f = self.region.i, self.region.f
        give_up_ns = 0
        while True:
            s1 = int(i[_SEQ])
            if not s1 & 1:
                mode, track_id, t_ref = int(i[_MODE]), int(i[_TRACK_ID]), int(i[_T_REF])
                valid, exposure, stop_id, frame_seq = (int(i[_VALID_UNTIL]), int(i[_EXPOSURE]),
                                                       int(i[_STOP_ID]), int(i[_FRAME_SEQ]))
                self._pose[:] = f[_POSE:_POSE + 12]
                self._vel[:] = f[_VEL:_VEL + 6]
                scale, horizon, lead = float(f[_SCALE]), float(f[_HORIZON]), float(f[_LEAD])
                move_speed, move_accel = float(f[_MOVE_SPEED]), float(f[_MOVE_ACCEL])
                if int(i[_SEQ]) == s1:
                    break
            now = time.monotonic_ns()   # only once a write got in the way
            if give_up_ns == 0:
                give_up_ns = now + max_wait_ns
            elif now >= give_up_ns:
                return None
        out.seq, out.mode, out.track_id, out.t_ref_ns = s1, mode, track_id, t_ref
        out.valid_until_ns, out.exposure_t_ns = valid, exposure
        out.stop_id, out.frame_seq = stop_id, frame_seq
        out.R[:] = self._pose[:9].reshape(3, 3)
        out.t_mm[:] = self._pose[9:]
        out.v_mm_s[:] = self._vel[:3]
        out.w_rad_s[:] = self._vel[3:]
        out.speed_scale, out.max_horizon_s, out.lead_s = scale, horizon, lead
        out.move_speed_mm_s, out.move_accel_mm_s2 = move_speed, move_accel
        return out


# ---------------------------------------------------------------------------- state ring
# slot word offsets
_S_T, _S_CMD_T, _S_SAFETY, _S_MODE, _S_PERIOD, _S_SERVO_MODE = range(6)
_S_POSE = 8        # 12 words
_S_Q = 20          # 6 words
_S_SPEED = 26
SLOT_WORDS = 28
_HEAD = 0
_RING_HEADER = 4


@dataclass
class RingRecord:
    """One period's record (a reader's reusable buffer). Codes are the indices in the robot
    interface's enums' declaration order (see :mod:`hil.servo.codes`)."""

    t_ns: int = 0             # the robot state's sample time
    cmd_t_ns: int = 0         # when this period's command was sent (0: none)
    safety_code: int = 0
    mode_code: int = 0
    period: int = 0           # the loop's period index
    servo_mode: int = 0       # the ServoMode the loop was in
    pose: FloatArray = field(default_factory=lambda: np.zeros(12))   # R row-major, t mm
    q_rad: FloatArray = field(default_factory=lambda: np.zeros(6))
    tcp_speed_mm_s: float = 0.0


class StateRing:
    """Per-period records (module doc). One writer: the servo loop."""

    def __init__(self, region: ShmRegion, slots: int) -> None:
        if region.words < ring_words(slots):
            raise ValueError(f"ring of {slots} slots needs {ring_words(slots)} words")
        self.region = region
        self.slots = slots
        self._slot = np.zeros(SLOT_WORDS)

    @property
    def head(self) -> int:
        """Records written so far."""
        return int(self.region.i[_HEAD])

    def _base(self, k: int) -> int:
        return _RING_HEADER + (k % self.slots) * SLOT_WORDS

    def write(self, *, t_ns: int, cmd_t_ns: int, safety_code: int, mode_code: int, period: int,
              servo_mode: int, pose: FloatArray, q_rad: FloatArray, tcp_speed_mm_s: float) -> None:
        i, f = self.region.i, self.region.f
        head = int(i[_HEAD])
        b = self._base(head)
        i[b + _S_T], i[b + _S_CMD_T], i[b + _S_SAFETY] = t_ns, cmd_t_ns, safety_code
        i[b + _S_MODE], i[b + _S_PERIOD], i[b + _S_SERVO_MODE] = mode_code, period, servo_mode
        f[b + _S_POSE:b + _S_POSE + 12] = pose
        f[b + _S_Q:b + _S_Q + 6] = q_rad
        f[b + _S_SPEED] = tcp_speed_mm_s
        i[_HEAD] = head + 1

    def read_latest(self, out: RingRecord) -> RingRecord | None:
        """The newest record copied into ``out``; None before the first."""
        return self.read_back(0, out)

    def read_back(self, back: int, out: RingRecord) -> RingRecord | None:
        """The record ``back`` periods before the newest (0: the newest) into ``out``; None when
        it does not exist (yet) or was overwritten while being read."""
        i, f = self.region.i, self.region.f
        if not 0 <= back < self.slots - 1:
            return None
        while True:
            h1 = int(i[_HEAD])
            k = h1 - 1 - back
            if k < 0:
                return None
            b = self._base(k)
            self._slot[:] = f[b:b + SLOT_WORDS]
            h2 = int(i[_HEAD])
            if h2 - h1 < self.slots - 1 - back:
                break
        raw = self._slot.view(np.int64)
        out.t_ns, out.cmd_t_ns, out.safety_code = int(raw[_S_T]), int(raw[_S_CMD_T]), int(raw[_S_SAFETY])
        out.mode_code, out.period = int(raw[_S_MODE]), int(raw[_S_PERIOD])
        out.servo_mode = int(raw[_S_SERVO_MODE])
        out.pose[:] = self._slot[_S_POSE:_S_POSE + 12]
        out.q_rad[:] = self._slot[_S_Q:_S_Q + 6]
        out.tcp_speed_mm_s = float(self._slot[_S_SPEED])
        return out


def ring_words(slots: int) -> int:
    return _RING_HEADER + slots * SLOT_WORDS


# ---------------------------------------------------------------------------- loop statistics
class Stat(IntEnum):
    """Counter words of :class:`LoopStats` (servo loop writes, anyone reads)."""

    PERIODS = 0               # periods stepped
    COMMANDS = 1              # servo commands sent
    LATE = 2                  # intervals longer than two periods
    MAX_INTERVAL_NS = 3
    STOPS_SENT = 4            # stop commands delivered to the driver
    STOP_ACK_ID = 5           # the last stop request id delivered
    STOP_ACK_T_NS = 6         # when it was delivered (controller clock)
    REFUSALS = 7              # setpoints the merged limit check refused (the loop then stops)
    STALE = 8                 # periods on a stale setpoint (ramping down to hold)
    READ_ERRORS = 9           # robot state reads that raised
    COMMAND_ERRORS = 10       # servo / stop commands the driver raised on
    INTERVALS = 11            # intervals measured (histogram total)
    LATENCY_SAMPLES = 12      # setpoints whose first command was measured
    LAST_PERIOD_T_NS = 13
    WORST_OVERRUN_NS = 14     # longest time a period's work ran past the next deadline, ns (*)
    STEP_NS_MAX = 15          # longest step() work, ns (*)
    STOP_ISSUE_ID = 16        # the last stop request the loop began to send
    STOP_ISSUE_T_NS = 17      # when it began (the driver's stop call may then block until rest)
    FOLLOWING_FAULTS = 18     # tracking sessions ended because the arm did not follow
    FOLLOWING_PEAK_UM = 19    # the largest following error seen, µm (hil.safety.following)
    WAKE_LATE_MAX_NS = 20     # longest the loop woke after its deadline, ns (*)
    LATE_WAKES = 21           # periods woken more than a period after their deadline (the OS or
                              # the host did not run the loop) (*)
    OVERRUNS = 22             # periods whose work ran more than a period past the next deadline
                              # (wall time: a preemption during the work counts here too) (*)
    SETPOINT_BUSY = 23        # periods the setpoint block was being written for the whole read
                              # (the loop went on with its last copy)
    OVERRUNS_OFF_CPU = 24     # overruns during whose work the loop's thread was off its CPU for
                              # more than a period (wall time minus the thread's CPU time: the
                              # host or the OS took the CPU, or the step blocked; the rest of
                              # OVERRUNS ran long on it) (*)
    STEP_CPU_NS_MAX = 25      # longest step() work in the loop thread's own CPU time, ns (*)
    STEP_OFF_CPU_NS_MAX = 26  # longest time the loop thread was off its CPU during one step, ns (*)
    MOVE_DONE_ID = 27         # the session id of the last MOVE whose profile has ended (the
                              # command is its target; the arm settles within its servo lag)
    # (*) written by the real-time host (hil/servo/process.py), from its 100th period on; an
    #     in-process loop stepped on a manual clock leaves them 0


STAT_WORDS = 32
#: interval histogram: bins of 10 µs over 0..20 ms (the last bin counts everything longer)
INTERVAL_BIN_NS = 10_000
INTERVAL_BINS = 2000
#: latency histogram (exposure -> first command on that setpoint): bins of 0.1 ms over 0..500 ms
LATENCY_BIN_NS = 100_000
LATENCY_BINS = 5000


def stats_words() -> int:
    return STAT_WORDS + INTERVAL_BINS + LATENCY_BINS


class LoopStats:
    """Counters and histograms of the servo loop (module doc)."""

    def __init__(self, region: ShmRegion, offset: int = 0) -> None:
        self.region = region
        self.offset = offset
        self.c: IntArray = region.i[offset:offset + STAT_WORDS]
        self.interval_hist: IntArray = region.i[offset + STAT_WORDS:offset + STAT_WORDS + INTERVAL_BINS]
        lo = offset + STAT_WORDS + INTERVAL_BINS
        self.latency_hist: IntArray = region.i[lo:lo + LATENCY_BINS]

    def get(self, stat: Stat) -> int:
        return int(self.c[stat])

    def add_interval(self, interval_ns: int, period_ns: int) -> None:
        c = self.c
        k = interval_ns // INTERVAL_BIN_NS
        self.interval_hist[k if k < INTERVAL_BINS else INTERVAL_BINS - 1] += 1
        c[Stat.INTERVALS] += 1
        if interval_ns > 2 * period_ns:
            c[Stat.LATE] += 1
        if interval_ns > c[Stat.MAX_INTERVAL_NS]:
            c[Stat.MAX_INTERVAL_NS] = interval_ns

    def add_latency(self, latency_ns: int) -> None:
        k = max(latency_ns, 0) // LATENCY_BIN_NS
        self.latency_hist[k if k < LATENCY_BINS else LATENCY_BINS - 1] += 1
        self.c[Stat.LATENCY_SAMPLES] += 1

    def reset(self) -> None:
        """Zero every counter and histogram (a soak's warm-up is left out this way)."""
        self.c[:] = 0
        self.interval_hist[:] = 0
        self.latency_hist[:] = 0


def histogram_percentile_ms(hist: IntArray, bin_ns: int, q: float) -> float | None:
    """The ``q`` (0..100) percentile of a histogram, ms (the upper edge of its bin; None: empty)."""
    total = int(hist.sum())
    if total == 0:
        return None
    rank = q / 100.0 * total
    k = int(np.searchsorted(np.cumsum(hist), rank, side="left"))
    return (min(k, hist.size - 1) + 1) * bin_ns * 1e-6
