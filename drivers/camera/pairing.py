"""Left/right frame pairing for stereo sources made of two independent cameras.

The pair rule, in order of preference (device-protocols.md C.4):

1. **trigger id** — the host issued trigger *k* to both cameras (software trigger); a frame's
   trigger id is its position in the camera's frame-id sequence since the first triggered frame.
   For a hardware trigger line driving both cameras (``frame_id`` rule) the two frame counters
   may be offset (the cameras started at different pulses): the offset is learned from the first
   pair matched by host time, and learned again whenever an id pair's host times disagree by
   more than half a period (a camera missed a pulse).
2. **device timestamps** — both camera clocks on one time base (PTP, or the host wall clock as in
   Aravis' fake cameras): the nearest ``device_t_ns`` within half a frame period.
3. **host time** — the nearest ``Frame.t_ns`` (host receive/kernel time on the controller clock)
   within half a frame period.

The pairer is pure logic (no device, no clock): drivers push frames as they arrive and ask for
the newest complete pair newer than the last one returned. Older unpaired frames are dropped.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal

from drivers.interfaces.camera import Frame, StereoFrame

Side = Literal["left", "right"]


class PairRule(StrEnum):
    TRIGGER_ID = "trigger_id"
    FRAME_ID = "frame_id"
    DEVICE_TIME = "device_time"
    HOST_TIME = "host_time"


class FrameIdUnwrapper:
    """Unwraps a wrapping device frame counter into a monotonic index.

    GigE Vision 1.x block ids are 16 bit and skip 0: they run 1..65535 then 1 again, a cycle of
    ``modulus`` = 65535 values. A backward step is taken as a wrap (frames are never reordered
    by a stream). The first value seen gives index 0.
    """

    def __init__(self, modulus: int = 65535) -> None:
        self.modulus = modulus
        self._last_raw: int | None = None
        self._index = -1

    def __call__(self, raw_id: int) -> int:
        if self._last_raw is None:
            self._index = 0
        else:
            step = (raw_id - self._last_raw) % self.modulus
            self._index += step if step != 0 else self.modulus
        self._last_raw = raw_id
        return self._index


@dataclass(frozen=True)
class _Tagged:
    frame: Frame
    key: int | None  # trigger id / rebased frame index for the id rules


class StereoPairer:
    """Pairs frames from two streams by ``rule``.

    Args:
        rule: how to decide that a left and a right frame belong together.
        period_ns: frame period, ns; the time rules accept a pair only within ``period_ns / 2``.
        max_pending: frames kept per side while waiting for the other side.
    """

    def __init__(self, rule: PairRule, period_ns: int, max_pending: int = 16) -> None:
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        self.rule = rule
        self.period_ns = period_ns
        self._pending: dict[Side, deque[_Tagged]] = {
            "left": deque(maxlen=max_pending),
            "right": deque(maxlen=max_pending),
        }
        self._last_key: int | None = None
        self._last_t_ns: int | None = None
        self.dropped = 0  # frames discarded unpaired
        self.realigned = 0  # frame_id rule: times the left/right id offset had to be learned again
        self._id_offset: int | None = None  # frame_id rule: left key - right key of a pair

    def push(self, side: Side, frame: Frame, key: int | None = None) -> None:
        """Add a frame. ``key`` is the trigger id / rebased frame index (id rules only)."""
        if self.rule in (PairRule.TRIGGER_ID, PairRule.FRAME_ID) and key is None:
            raise ValueError(f"rule {self.rule} needs a key for every frame")
        queue = self._pending[side]
        if queue.maxlen is not None and len(queue) == queue.maxlen:
            self.dropped += 1
        queue.append(_Tagged(frame, key))

    def pending(self, side: Side) -> int:
        return len(self._pending[side])

    def pop_pair(self, min_key: int | None = None) -> StereoFrame | None:
        """The newest complete pair newer than the last one returned, or None.

        ``min_key`` (id rules): accept only pairs whose key is at least this (a software-trigger
        driver passes the trigger it just issued, so a late pair of an older trigger is not
        returned as fresh). Frames older than the returned pair (on either side) are discarded.
        """
        left, right = self._pending["left"], self._pending["right"]
        best: tuple[_Tagged, _Tagged] | None
        if self.rule is PairRule.TRIGGER_ID:
            best = self._newest_by_key(left, right, min_key, 0)
        elif self.rule is PairRule.FRAME_ID:
            best = self._by_frame_id(left, right, min_key)
        else:
            best = self._newest_by_time(left, right)
        if best is None:
            return None
        l_tag, r_tag = best
        self._discard_up_to(l_tag, r_tag)
        self._last_key = l_tag.key
        pair = StereoFrame(left=l_tag.frame, right=r_tag.frame)
        self._last_t_ns = pair.t_ns
        return pair

    def _newest_by_key(self, left: deque[_Tagged], right: deque[_Tagged], min_key: int | None,
                       right_offset: int) -> tuple[_Tagged, _Tagged] | None:
        right_by_key = {(tagged.key or 0) + right_offset: tagged for tagged in right}
        for tagged in reversed(left):
            key = tagged.key if tagged.key is not None else 0
            other = right_by_key.get(key)
            if other is None or (self._last_key is not None and key <= self._last_key):
                continue
            if min_key is None or key >= min_key:
                return tagged, other
        return None

    def _by_frame_id(self, left: deque[_Tagged], right: deque[_Tagged], min_key: int | None
                     ) -> tuple[_Tagged, _Tagged] | None:
        """Frame-id pairing, its left/right id offset learned (and re-learned) from host time.

        The offset between the two counters is taken from the first pair matched by host time.
        An id pair whose host times differ by more than half a period means the counters went
        out of step (a camera missed a pulse or dropped a frame): the offset is learned again.
        """
        if self._id_offset is not None:
            best = self._newest_by_key(left, right, min_key, self._id_offset)
            if best is None:
                return None
            if abs(best[0].frame.t_ns - best[1].frame.t_ns) <= self.period_ns // 2:
                return best
        by_time = self._newest_by_time(left, right)
        if by_time is None:
            return None
        offset = (by_time[0].key or 0) - (by_time[1].key or 0)
        if self._id_offset is not None and offset != self._id_offset:
            self.realigned += 1
        self._id_offset = offset
        return by_time

    def _time(self, tagged: _Tagged) -> int:
        if self.rule is PairRule.DEVICE_TIME:
            if tagged.frame.device_t_ns is None:
                raise ValueError("rule device_time needs frames with device_t_ns")
            return tagged.frame.device_t_ns
        return tagged.frame.t_ns

    def _newest_by_time(
        self, left: deque[_Tagged], right: deque[_Tagged]
    ) -> tuple[_Tagged, _Tagged] | None:
        half_ns = self.period_ns // 2
        for l_tag in reversed(left):
            if self._last_t_ns is not None and l_tag.frame.t_ns <= self._last_t_ns:
                break
            t_left = self._time(l_tag)
            nearest = min(right, key=lambda r: abs(self._time(r) - t_left), default=None)
            if nearest is not None and abs(self._time(nearest) - t_left) <= half_ns:
                if self._last_t_ns is not None and nearest.frame.t_ns <= self._last_t_ns:
                    continue
                return l_tag, nearest
        return None

    def _discard_up_to(self, l_tag: _Tagged, r_tag: _Tagged) -> None:
        pairs: tuple[tuple[Side, _Tagged], ...] = (("left", l_tag), ("right", r_tag))
        for side, tag in pairs:
            queue = self._pending[side]
            while queue:
                head = queue.popleft()
                if head is tag:
                    break
                self.dropped += 1
