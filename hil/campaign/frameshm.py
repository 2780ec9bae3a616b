"""A stereo pair in shared memory: one writer process, any number of reader processes.

The camera scenario of the transport tier (:mod:`hil.campaign.gige`) renders the simulated world in
the run's process and serves it from fake GigE Vision cameras in another process
(``tools/fakegv --shm NAME``); this block carries the newest pair between them.

Layout (little-endian, native alignment), a POSIX shared-memory object ``/dev/shm/<name>``:

====== ======= ==============================================================
offset type    field
====== ======= ==============================================================
0      u64     magic ``HILFRAME`` (as bytes)
8      u64     capacity_px: bytes reserved per image (max width x height)
16     u64     seq: seqlock counter (odd while a pair is being written)
24     u64     width_px
32     u64     height_px
40     u64     pair_no: pairs written so far (1 = the first)
48     i64     t_ns: the pair's exposure time on the writer's clock
56     u8[]    left image (Mono8, row-major, width x height), then the right one at 56 + capacity_px
====== ======= ==============================================================

**Seqlock**: the writer makes ``seq`` odd, writes the header fields and both images, then makes it
even again. A reader copies everything and accepts the copy only when ``seq`` was even and the
same before and after: a reader never returns a torn pair (half old, half new; or a left image of
one pair with the right image of another). Single writer only.
"""

from __future__ import annotations

import contextlib
import mmap
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from hil.errors import HilError
from hil.servo.shm import close_segment

U8Image = NDArray[np.uint8]

MAGIC = int.from_bytes(b"HILFRAME", "little")
HEADER_BYTES = 56
_MAGIC, _CAPACITY, _SEQ, _WIDTH, _HEIGHT, _PAIR_NO, _T_NS = range(7)


class FrameBlockError(HilError):
    """The shared-memory block is missing, not a frame block, or too small for a pair."""


@dataclass(frozen=True)
class SharedPair:
    """One consistent snapshot of the block (copies, safe to keep)."""

    pair_no: int
    t_ns: int
    left: U8Image
    right: U8Image

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height)."""
        return (int(self.left.shape[1]), int(self.left.shape[0]))


def block_bytes(capacity_px: int) -> int:
    """Size of a block holding two images of up to ``capacity_px`` bytes."""
    return HEADER_BYTES + 2 * capacity_px


class _View:
    """Header and image views onto a buffer of the block layout.

    The views are ``np.frombuffer`` arrays: each keeps the buffer exported while it lives, so the
    mapping under it cannot be closed (a view read after an unmap would crash the process); an
    ``np.ndarray(buffer=...)`` view holds no export and would be left dangling."""

    def __init__(self, buf: memoryview) -> None:
        self.buf = buf
        self.header = np.frombuffer(buf, dtype=np.uint64, count=7, offset=0)

    @property
    def capacity_px(self) -> int:
        return int(self.header[_CAPACITY])

    def image(self, side: int, width_px: int, height_px: int) -> U8Image:
        offset = HEADER_BYTES + side * self.capacity_px
        flat = np.frombuffer(self.buf, dtype=np.uint8, count=width_px * height_px, offset=offset)
        return flat.reshape(height_px, width_px)

    def release(self) -> bool:
        """Drop the header view and release the buffer; False when another view still holds it
        (the mapping then goes with the last view)."""
        del self.header
        try:
            self.buf.release()
        except BufferError:
            return False
        return True


class FrameBlockWriter:
    """Creates the block (``name`` None: a fresh random name) and writes pairs into it.

    Args:
        capacity_px: the largest width x height that will be written.
        name: the shared-memory name (without ``/``); must not exist yet.

    Raises:
        FrameBlockError: the block cannot be created (name taken, no /dev/shm space).
    """

    def __init__(self, capacity_px: int, name: str | None = None) -> None:
        if capacity_px <= 0:
            raise FrameBlockError(f"frame block: capacity must be > 0 px, got {capacity_px}")
        try:
            shm = shared_memory.SharedMemory(name=name, create=True, size=block_bytes(capacity_px))
        except OSError as exc:
            raise FrameBlockError(f"frame block {name!r}: cannot create: {exc}") from exc
        self._shm: shared_memory.SharedMemory | None = shm
        assert shm.buf is not None
        self._view = _View(shm.buf)
        h = self._view.header
        h[:] = 0
        h[_CAPACITY] = capacity_px
        h[_MAGIC] = MAGIC
        self.pairs_written = 0

    @property
    def name(self) -> str:
        """The block's name (what ``tools/fakegv --shm`` takes)."""
        assert self._shm is not None, "frame block closed"
        return self._shm.name

    def begin(self) -> None:
        """Open a write (``seq`` odd). :meth:`write` calls it; public for the torn-read tests."""
        self._view.header[_SEQ] += np.uint64(1)

    def end(self) -> None:
        """Close a write (``seq`` even again)."""
        self._view.header[_SEQ] += np.uint64(1)

    def write(self, left: U8Image, right: U8Image, t_ns: int) -> int:
        """Publish one pair (HxW uint8 each, same shape); returns its ``pair_no``. Non-blocking.

        Raises:
            FrameBlockError: bad shape/dtype, or larger than the block's capacity.
        """
        if left.dtype != np.uint8 or left.ndim != 2 or left.shape != right.shape or right.dtype != np.uint8:
            raise FrameBlockError(f"frame block: a pair is two equal HxW uint8 images, got "
                                  f"{left.dtype}{left.shape} and {right.dtype}{right.shape}")
        height, width = left.shape
        if width * height > self._view.capacity_px:
            raise FrameBlockError(f"frame block: {width}x{height} exceeds the capacity "
                                  f"({self._view.capacity_px} px)")
        h = self._view.header
        self.begin()
        try:
            h[_WIDTH], h[_HEIGHT] = width, height
            h[_PAIR_NO] = self.pairs_written + 1
            h[_T_NS] = np.int64(t_ns).view(np.uint64)
            self._view.image(0, width, height)[:] = left
            self._view.image(1, width, height)[:] = right
        finally:
            self.end()
        self.pairs_written += 1
        return self.pairs_written

    def close(self) -> None:
        """Release and unlink the block (idempotent). A view of it still alive elsewhere keeps
        the mapping (unlinked) until a later close finds it free: never unmapped under a reader."""
        shm, self._shm = self._shm, None
        if shm is None:
            return
        self._view.release()
        close_segment(shm)
        with contextlib.suppress(FileNotFoundError):
            shm.unlink()


class FrameBlockReader:
    """Attaches to an existing block by name (read-only use; no resource tracker involved, so a
    reader exiting never unlinks the writer's block).

    Raises:
        FrameBlockError: no such block, or not a frame block.
    """

    def __init__(self, name: str) -> None:
        path = Path("/dev/shm") / name.lstrip("/")
        try:
            with path.open("r+b") as f:
                self._map = mmap.mmap(f.fileno(), 0)
        except (OSError, ValueError) as exc:
            raise FrameBlockError(f"frame block {name!r}: cannot attach ({path}): {exc}") from exc
        if len(self._map) < HEADER_BYTES:
            self._map.close()
            raise FrameBlockError(f"frame block {name!r}: {len(self._map)} bytes, not a frame block")
        self._view = _View(memoryview(self._map))
        h = self._view.header
        if int(h[_MAGIC]) != MAGIC or len(self._map) < block_bytes(int(h[_CAPACITY])):
            self.close()
            raise FrameBlockError(f"frame block {name!r}: bad magic or size, not a frame block")
        self.name = name
        self.torn_reads = 0

    def read(self, attempts: int = 50, *, on_copied: Callable[[], object] | None = None) -> SharedPair | None:
        """The newest complete pair, or None when none was written yet or no consistent copy was
        obtained in ``attempts`` tries (each retry after 0.5 ms). Blocks at most ~``attempts`` x
        0.5 ms plus the copies. ``on_copied`` runs between the copy and the consistency check
        (tests use it to write meanwhile)."""
        h = self._view.header
        for i in range(attempts):
            if i:
                time.sleep(0.0005)
            seq = int(h[_SEQ])
            if seq == 0:
                return None
            if seq % 2:
                self.torn_reads += 1
                continue
            width, height = int(h[_WIDTH]), int(h[_HEIGHT])
            pair_no, t_ns = int(h[_PAIR_NO]), int(np.uint64(h[_T_NS]).view(np.int64))
            if width * height > self._view.capacity_px:
                self.torn_reads += 1
                continue
            left = self._view.image(0, width, height).copy()
            right = self._view.image(1, width, height).copy()
            if on_copied is not None:
                on_copied()
            if int(h[_SEQ]) == seq:
                return SharedPair(pair_no, t_ns, left, right)
            self.torn_reads += 1
        return None

    def close(self) -> None:
        """Detach (idempotent). A view of the block still alive elsewhere keeps the mapping
        until it is collected (never unmapped under a reader)."""
        if self._map.closed:
            return
        if self._view.release():
            with contextlib.suppress(BufferError):
                self._map.close()

