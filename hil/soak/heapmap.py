"""Where the supervisor's resident memory is: a breakdown the soak takes once a minute.

Why (issue 45, docs/benchmarks.md "The hour at 500 Hz"): the supervisor's resident size stepped
up 4-8 MB at some later faults of an hour and kept the step through every heap trim. RSS alone
cannot say who holds it (it was stereo pairs held by reference cycles through a fault's exceptions,
which CPython's collector left for minutes: hil/heap.py part 3). Three owners can:

- glibc's heap (``mallinfo2``): bytes in use (``c_in_use_mb``: what the program holds through
  ``malloc``, numpy's buffers included), free inside the heap (``c_free_mb``: what a trim may
  return only as whole pages), and large chunks served by ``mmap`` (``c_mmapped_mb``);
- CPython's object allocator: ``sys.getallocatedblocks()`` (live small objects) and its arenas,
  which are anonymous 1 MiB ``mmap`` regions that are freed only when every object in them is;
- the mappings' resident sizes by kind (``/proc/self/smaps``): the brk heap (``[heap]``, glibc's
  main arena), anonymous mappings (CPython's arenas, glibc's ``mmap`` chunks, thread stacks) and
  file-backed ones (code, shared memory with the servo process).

A step that is in ``c_in_use_mb`` is held by the program (a cache, a buffer kept); one in
``c_free_mb`` with unchanged use is fragmentation glibc cannot return; one in ``anon_rss_mb`` with
neither is CPython's arenas (or an ``mmap`` outside malloc). Linux with glibc only: elsewhere
each unreadable figure is None, never guessed.

File-backed pages are also kept per file (``file_rss_kb_by_path``): a step there is code or data
of a library paged in for the first time (the first fault's path), which :func:`file_growth`
names.

Reading ``smaps`` walks every mapping (~20 ms for the supervisor, most of it parsing under the
GIL): once a minute, from the soak's operator thread, never the servo loop.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from dataclasses import asdict, dataclass

__all__ = ["HeapBreakdown", "file_growth", "parse_smaps_file_rss_kb", "parse_smaps_rss_kb",
           "read_heap_breakdown"]

_MB = 2.0**20


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (malloc.h, glibc >= 2.33): ten ``size_t`` fields, bytes."""

    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


def _mallinfo2() -> _MallInfo2 | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    fn = getattr(libc, "mallinfo2", None)
    if fn is None:
        return None
    fn.argtypes = []
    fn.restype = _MallInfo2
    info: _MallInfo2 = fn()
    return info


@dataclass(frozen=True)
class HeapBreakdown:
    """One reading (module doc). Sizes in MB; None where the figure could not be read.

    Attributes:
        c_in_use_mb: glibc heap in use, arenas plus ``mmap`` chunks (``uordblks + hblkhd``).
        c_free_mb: free inside glibc's arenas (``fordblks``).
        c_mmapped_mb: glibc chunks served by ``mmap`` (``hblkhd``).
        python_blocks: CPython's live small-object blocks (``sys.getallocatedblocks()``).
        heap_rss_mb: resident size of the ``[heap]`` mapping (glibc's main arena).
        anon_rss_mb: resident size of anonymous mappings (CPython's arenas, ``mmap`` chunks,
            thread stacks, other arenas).
        file_rss_mb: resident size of file-backed mappings (code, shared memory).
        file_rss_kb_by_path: resident kB of each mapped file, path-sorted (None when smaps could
            not be read); not in :meth:`to_dict` (a few hundred files).
    """

    c_in_use_mb: float | None
    c_free_mb: float | None
    c_mmapped_mb: float | None
    python_blocks: int
    heap_rss_mb: float | None
    anon_rss_mb: float | None
    file_rss_mb: float | None
    file_rss_kb_by_path: tuple[tuple[str, int], ...] | None = None

    def to_dict(self) -> dict[str, float | int | None]:
        return {k: (round(v, 2) if isinstance(v, float) else v) for k, v in asdict(self).items()
                if k != "file_rss_kb_by_path"}


def parse_smaps_rss_kb(text: str) -> dict[str, int]:
    """Resident kB of ``/proc/<pid>/smaps`` text by kind of mapping: ``heap`` (``[heap]``),
    ``anon`` (no path, or ``[anon:...]``, ``[stack...]``) and ``file`` (a path, ``/dev/shm``
    included); ``[vdso]``-like special mappings count as ``anon``. Lines that are neither a
    mapping header nor ``Rss:`` are skipped; a malformed ``Rss:`` line raises ValueError naming it.
    """
    out = {"heap": 0, "anon": 0, "file": 0}
    kind = "anon"
    for line in text.splitlines():
        head = line.split(maxsplit=5)
        if not head:
            continue
        if "-" in head[0] and ":" not in head[0]:           # a mapping header: addr-addr perms ...
            path = head[5].strip() if len(head) == 6 else ""
            kind = ("heap" if path == "[heap]" else "file" if path.startswith("/") else "anon")
        elif head[0] == "Rss:":
            if len(head) < 2 or not head[1].isdigit():
                raise ValueError(f"smaps: unreadable Rss line {line!r}")
            out[kind] += int(head[1])
    return out


def parse_smaps_file_rss_kb(text: str) -> dict[str, int]:
    """Resident kB of each file-backed mapping's file (a path; the mappings of one file summed)
    in ``/proc/<pid>/smaps`` text. A malformed ``Rss:`` line raises ValueError naming it."""
    out: dict[str, int] = {}
    path = ""
    for line in text.splitlines():
        head = line.split(maxsplit=5)
        if not head:
            continue
        if "-" in head[0] and ":" not in head[0]:
            path = head[5].strip() if len(head) == 6 else ""
        elif head[0] == "Rss:" and path.startswith("/"):
            if len(head) < 2 or not head[1].isdigit():
                raise ValueError(f"smaps: unreadable Rss line {line!r}")
            out[path] = out.get(path, 0) + int(head[1])
    return out


def file_growth(readings: list[tuple[float, HeapBreakdown]], t_from: float, t0: float,
                min_kb: int = 64, top: int = 12) -> list[dict[str, str | int | float]]:
    """The files whose resident pages grew by ``min_kb`` or more from the first reading at or
    after ``t_from`` to the last (monotonic s), largest first, at most ``top``: ``file``, ``kb``
    (the growth) and ``first_grew_min`` (minutes from ``t0`` of the first reading at which it had
    grown). Readings without the per-file figure are skipped; fewer than two: an empty list."""
    usable = [(t, dict(b.file_rss_kb_by_path)) for t, b in readings
              if b.file_rss_kb_by_path is not None and t >= t_from]
    if len(usable) < 2:
        return []
    base, last = usable[0][1], usable[-1][1]
    out: list[dict[str, str | int | float]] = []
    for path, kb in last.items():
        grown = kb - base.get(path, 0)
        if grown < min_kb:
            continue
        first = next(t for t, files in usable[1:] if files.get(path, 0) - base.get(path, 0) > 0)
        out.append({"file": path, "kb": grown, "first_grew_min": round((first - t0) / 60.0, 2)})
    out.sort(key=lambda row: (-int(row["kb"]), str(row["file"])))
    return out[:top]


def read_heap_breakdown(smaps_path: str = "/proc/self/smaps") -> HeapBreakdown:
    """This process's breakdown now (module doc). Never raises; what it cannot read is None."""
    info = _mallinfo2()
    by_path: tuple[tuple[str, int], ...] | None
    try:
        with open(smaps_path) as fh:
            text = fh.read()
        kb: dict[str, int] | None = parse_smaps_rss_kb(text)
        by_path = tuple(sorted(parse_smaps_file_rss_kb(text).items()))
    except (OSError, ValueError):
        kb, by_path = None, None
    return HeapBreakdown(
        c_in_use_mb=None if info is None else (info.uordblks + info.hblkhd) / _MB,
        c_free_mb=None if info is None else info.fordblks / _MB,
        c_mmapped_mb=None if info is None else info.hblkhd / _MB,
        python_blocks=sys.getallocatedblocks(),
        heap_rss_mb=None if kb is None else kb["heap"] / 1024.0,
        anon_rss_mb=None if kb is None else kb["anon"] / 1024.0,
        file_rss_mb=None if kb is None else kb["file"] / 1024.0,
        file_rss_kb_by_path=by_path)
