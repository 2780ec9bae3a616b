"""The marker-set ring: the perception process publishes one record per stereo pair (or per
failure) into shared memory; the supervisor reads the newest.

One writer (the perception process), any number of readers, no locks. The writer fills slot
``head % SLOTS`` and then increments the header word ``head``; a reader copies slot ``head - 1``
in one block and accepts the copy when ``head`` moved by fewer than ``SLOTS - 1`` meanwhile (the
slot was not being rewritten under it), else it retries. Ordering as in :mod:`hil.servo.shm`
(plain 8-byte words, x86-64 total store order).

Record layout (8-byte words; the header is int64, the arrays float64):

====  ==========================================================================
word  field
====  ==========================================================================
0     kind: 0 markers, 1 grab error (the camera raised), 2 locate error
1     pair sequence: 1, 2, ... in the order the process produced its records
2, 3  left / right frame counter (``Frame.seq``)
4, 5  left / right exposure (or reception) time ``Frame.t_ns``, controller clock
6, 7  left / right ``Frame.device_t_ns`` (see flags)
8     flags: bit 0 / 1 left / right device time present; bit 2 / 3 left / right per-camera
      centres known
9     time source of both frames (0 exposure, 1 reception: :class:`FrameTime` order)
10    grab done: the clock when the camera returned the pair, ns
11    locate time, ms (float64)
12,13 image width, height, px
14-16 counts: left centres, right centres, triangulated points
24..  left centres (MAX_MARKERS x 2, px), right centres (MAX_MARKERS x 2, px), points
      (MAX_MARKERS x 3, optical frame, mm); an error record instead holds its text here:
      ``class\\x00device\\x00message`` UTF-8, at most ERROR_BYTES bytes
====  ==========================================================================

At most :data:`MAX_MARKERS` markers per camera and triangulated: a pair with more is published
as a locate error naming the count (never truncated silently).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from hil.servo.shm import ShmRegion

FloatArray = NDArray[np.float64]

#: Markers per camera and triangulated a record holds.
MAX_MARKERS = 64
#: Records the ring keeps (the supervisor reads the newest; older ones are history).
SLOTS = 16

_HEADER = 24
_LEFT = _HEADER
_RIGHT = _LEFT + 2 * MAX_MARKERS
_POINTS = _RIGHT + 2 * MAX_MARKERS
RECORD_WORDS = _POINTS + 3 * MAX_MARKERS
ERROR_BYTES = (RECORD_WORDS - _HEADER) * 8
_RING_HEADER = 8
_HEAD = 0

(_KIND, _PAIR, _LSEQ, _RSEQ, _LT, _RT, _LDEV, _RDEV, _FLAGS, _SOURCE, _GRAB_DONE, _LOCATE_MS,
 _WIDTH, _HEIGHT, _NL, _NR, _NP) = range(17)

_F_LDEV, _F_RDEV, _F_LPX, _F_RPX = 1, 2, 4, 8


class RecordKind(IntEnum):
    """What a record holds."""

    MARKERS = 0
    GRAB_ERROR = 1
    LOCATE_ERROR = 2


def ring_words() -> int:
    """Words of the whole ring region."""
    return _RING_HEADER + SLOTS * RECORD_WORDS


@dataclass
class MarkerRecord:
    """One record, decoded (a copy; see the module doc for the fields).

    ``left_px`` / ``right_px`` are None when the locator did not say; ``error`` is
    ``(class name, device, message)`` for an error record, else None.
    """

    kind: RecordKind = RecordKind.MARKERS
    pair_seq: int = 0
    left_seq: int = 0
    right_seq: int = 0
    left_t_ns: int = 0
    right_t_ns: int = 0
    left_device_t_ns: int | None = None
    right_device_t_ns: int | None = None
    time_source: int = 0
    grab_done_t_ns: int = 0
    locate_ms: float = 0.0
    image_size: tuple[int, int] = (0, 0)
    points_mm: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    left_px: FloatArray | None = None
    right_px: FloatArray | None = None
    error: tuple[str, str, str] | None = None


class MarkerRing:
    """The ring over ``region`` (module doc). One writer; readers keep their own instance."""

    def __init__(self, region: ShmRegion) -> None:
        if region.words < ring_words():
            raise ValueError(f"marker ring needs {ring_words()} words, region has {region.words}")
        self.region = region
        self._copy = np.zeros(RECORD_WORDS)

    @property
    def head(self) -> int:
        """Records written so far."""
        return int(self.region.i[_HEAD])

    def _base(self, k: int) -> int:
        return _RING_HEADER + (k % SLOTS) * RECORD_WORDS

    # ------------------------------------------------------------------ writer
    def write_markers(self, *, pair_seq: int, left: tuple[int, int, int | None],
                      right: tuple[int, int, int | None], time_source: int, grab_done_t_ns: int,
                      locate_ms: float, image_size: tuple[int, int], points_mm: FloatArray,
                      left_px: FloatArray | None, right_px: FloatArray | None) -> None:
        """Publish a marker set. ``left`` / ``right``: (frame counter, t_ns, device t_ns or None).

        Raises:
            ValueError: more than :data:`MAX_MARKERS` markers in one of the sets (nothing written).
        """
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        sets = [("triangulated", pts)]
        sets += [(n, np.asarray(a, dtype=np.float64).reshape(-1, 2))
                 for n, a in (("left", left_px), ("right", right_px)) if a is not None]
        for what, a in sets:
            if a.shape[0] > MAX_MARKERS:
                raise ValueError(f"{a.shape[0]} {what} markers located, at most {MAX_MARKERS} fit a record")
        i, f = self.region.i, self.region.f
        head = int(i[_HEAD])
        b = self._base(head)
        flags = (_F_LDEV if left[2] is not None else 0) | (_F_RDEV if right[2] is not None else 0)
        i[b + _KIND], i[b + _PAIR] = RecordKind.MARKERS, pair_seq
        i[b + _LSEQ], i[b + _LT], i[b + _LDEV] = left[0], left[1], left[2] or 0
        i[b + _RSEQ], i[b + _RT], i[b + _RDEV] = right[0], right[1], right[2] or 0
        i[b + _SOURCE], i[b + _GRAB_DONE] = time_source, grab_done_t_ns
        f[b + _LOCATE_MS] = locate_ms
        i[b + _WIDTH], i[b + _HEIGHT] = image_size
        i[b + _NP] = pts.shape[0]
        f[b + _POINTS:b + _POINTS + pts.size] = pts.reshape(-1)
        cams: tuple[tuple[int, int, int, FloatArray | None], ...] = (
            (_LEFT, _NL, _F_LPX, left_px), (_RIGHT, _NR, _F_RPX, right_px))
        for offset, count, bit, cam in cams:
            if cam is None:
                i[b + count] = 0
                continue
            px = np.asarray(cam, dtype=np.float64).reshape(-1)
            flags |= bit
            i[b + count] = px.size // 2
            f[b + offset:b + offset + px.size] = px
        i[b + _FLAGS] = flags
        i[_HEAD] = head + 1

    def write_error(self, kind: RecordKind, pair_seq: int, error: tuple[str, str, str],
                    grab_done_t_ns: int) -> None:
        """Publish an error record: ``error`` is ``(class name, device, message)`` (the message is
        cut to fit :data:`ERROR_BYTES`)."""
        i = self.region.i
        head = int(i[_HEAD])
        b = self._base(head)
        text = "\x00".join(error).encode("utf-8", "replace")[:ERROR_BYTES]
        i[b:b + _HEADER] = 0
        i[b + _KIND], i[b + _PAIR], i[b + _GRAB_DONE] = kind, pair_seq, grab_done_t_ns
        i[b + _NL] = len(text)   # the text's length in bytes
        raw = self.region.i[b + _HEADER:b + RECORD_WORDS].view(np.uint8)
        raw[:len(text)] = np.frombuffer(text, dtype=np.uint8)
        i[_HEAD] = head + 1

    # ------------------------------------------------------------------ reader
    def read_latest(self) -> MarkerRecord | None:
        """A copy of the newest record; None before the first. Never blocks (retries a copy the
        writer overran)."""
        while True:
            h1 = self.head
            if h1 == 0:
                return None
            self._copy_slot(h1 - 1)
            if self._still_valid(h1):
                return _decode(self._copy)

    def _copy_slot(self, k: int) -> None:
        b = self._base(k)
        self._copy[:] = self.region.f[b:b + RECORD_WORDS]

    def _still_valid(self, h1: int) -> bool:
        """Whether slot ``h1 - 1`` was not rewritten since ``head`` read ``h1``."""
        return self.head - h1 < SLOTS - 1


def _decode(w: FloatArray) -> MarkerRecord:
    raw = w.view(np.int64)
    h = raw[:_HEADER].tolist()   # the header as Python ints at once (a record per pair, on its path)
    kind = RecordKind(h[_KIND])
    rec = MarkerRecord(kind=kind, pair_seq=h[_PAIR], grab_done_t_ns=h[_GRAB_DONE])
    if kind is not RecordKind.MARKERS:
        n = h[_NL]
        text = raw[_HEADER:].view(np.uint8)[:n].tobytes().decode("utf-8", "replace")
        parts = [*text.split("\x00", 2), "", ""][:3]
        rec.error = (parts[0], parts[1], parts[2])
        return rec
    flags = h[_FLAGS]
    rec.left_seq, rec.right_seq = h[_LSEQ], h[_RSEQ]
    rec.left_t_ns, rec.right_t_ns = h[_LT], h[_RT]
    rec.left_device_t_ns = h[_LDEV] if flags & _F_LDEV else None
    rec.right_device_t_ns = h[_RDEV] if flags & _F_RDEV else None
    rec.time_source = h[_SOURCE]
    rec.locate_ms = float(w[_LOCATE_MS])
    rec.image_size = (h[_WIDTH], h[_HEIGHT])
    n_pts = min(h[_NP], MAX_MARKERS)
    rec.points_mm = w[_POINTS:_POINTS + 3 * n_pts].reshape(-1, 3).copy()
    if flags & _F_LPX:
        n = min(h[_NL], MAX_MARKERS)
        rec.left_px = w[_LEFT:_LEFT + 2 * n].reshape(-1, 2).copy()
    if flags & _F_RPX:
        n = min(h[_NR], MAX_MARKERS)
        rec.right_px = w[_RIGHT:_RIGHT + 2 * n].reshape(-1, 2).copy()
    return rec
