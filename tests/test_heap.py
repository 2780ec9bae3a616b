"""The supervisor's heap trim policy (hil/heap.py): the period on the caller's clock, the figures,
and the real glibc call."""

from __future__ import annotations

import gc
import weakref
from types import TracebackType

import numpy as np
import pytest

from hil.heap import HeapTrimmer, glibc_malloc_trim

S = 1_000_000_000


def test_trims_once_per_period_of_the_callers_clock() -> None:
    calls: list[int] = []
    answers = iter([1, 0, 1])

    def trim() -> int:
        calls.append(1)
        return next(answers)

    h = HeapTrimmer(10.0, trim=trim)
    for t in (0, 5 * S, 9 * S, 10 * S, 11 * S, 19 * S, 20 * S, 35 * S, 36 * S):
        h.after_tick(t)
    # the first call starts the period; then at 10 s, 20 s and 35 s (the next period runs from each trim)
    assert len(calls) == 3
    f = h.figures()
    assert (f.trims, f.released) == (3, 2)
    assert f.max_ms >= 0.0
    assert f.total_ms >= f.max_ms
    assert h.unavailable is None


def test_period_zero_never_trims() -> None:
    calls: list[int] = []

    def trim() -> int:
        calls.append(1)
        return 1

    h = HeapTrimmer(0.0, trim=trim)
    for t in range(0, 100 * S, S):
        h.after_tick(t)
    assert calls == []
    assert h.unavailable == "disabled (period 0)"
    h.start()
    assert gc.get_freeze_count() == 0
    for t in range(0, 100 * S, S):
        h.after_tick(t)
    h.stop()
    assert h.figures().to_dict() == {"trims": 0, "released": 0, "max_ms": 0.0, "total_ms": 0.0,
                                     "collections": 0, "collected": 0, "collect_max_ms": 0.0,
                                     "collect_total_ms": 0.0, "frozen_objects": 0}


def test_a_started_trimmer_collects_cycles_each_period_before_the_trim() -> None:
    """Between start and stop, each period first collects reference cycles, then trims; before
    start (and after stop) it only trims."""
    calls: list[str] = []

    def collect() -> int:
        calls.append("collect")
        return 7

    def trim() -> int:
        calls.append("trim")
        return 1

    h = HeapTrimmer(10.0, trim=trim, collect=collect)
    h.after_tick(0)
    h.after_tick(10 * S)
    assert calls == ["trim"]
    h.start()
    try:
        assert gc.get_freeze_count() > 0
        h.after_tick(20 * S)
        h.after_tick(25 * S)
        h.after_tick(30 * S)
    finally:
        h.stop()
    assert gc.get_freeze_count() == 0
    h.after_tick(40 * S)
    assert calls == ["trim", "collect", "trim", "collect", "trim", "trim"]
    f = h.figures()
    assert (f.trims, f.collections, f.collected) == (4, 2, 14)
    assert f.frozen_objects > 0
    assert f.collect_total_ms >= f.collect_max_ms >= 0.0


def test_the_freeze_lasts_until_the_last_started_trimmer_stops() -> None:
    """Two runs in one process (threads of a campaign, a console and a test): the first to stop
    leaves the objects frozen for the other; stop twice is harmless."""
    a, b = HeapTrimmer(10.0, trim=lambda: 0), HeapTrimmer(10.0, trim=lambda: 0)
    a.start()
    b.start()
    try:
        a.stop()
        a.stop()
        assert gc.get_freeze_count() > 0
    finally:
        b.stop()
    assert gc.get_freeze_count() == 0


class _Camera:
    """A grab that times out after dropping a pair, as the frame-drop fault's wrapper does."""

    def __init__(self) -> None:
        self.error: Exception | None = None

    def grab(self) -> None:
        pair = np.ones((1080, 1920, 2), np.uint8)   # the dropped pair, a local of the raising frame
        try:
            raise TimeoutError(f"no stereo pair within 0.27 s ({pair.shape})")
        except TimeoutError as exc:
            self.error = exc   # kept by the camera: camera -> exception -> traceback -> frame -> self


def test_a_started_trimmer_frees_a_pair_held_by_an_exceptions_cycle_within_a_period() -> None:
    """Issue 45's held pairs: a pair referenced only from a reference cycle through an exception's
    traceback stays allocated until a cyclic collection, which the supervisor's steady state almost
    never triggered (here the automatic collector is off, as it effectively was); a started
    trimmer frees it at its next period, and the trim returns its pages."""
    was_enabled = gc.isenabled()
    gc.disable()
    h = HeapTrimmer(10.0, collect=gc.collect)
    try:
        h.start()
        h.after_tick(0)
        cam = _Camera()
        cam.grab()
        frames = [tb.tb_frame for tb in _walk(cam.error)]
        pair = weakref.ref(frames[-1].f_locals["pair"])
        del cam, frames
        h.after_tick(5 * S)
        assert pair() is not None, "a cycle outlives its last outside reference until a collection"
        h.after_tick(10 * S)
        assert pair() is None
        assert h.figures().collected > 0
    finally:
        h.stop()
        if was_enabled:
            gc.enable()


def _walk(exc: BaseException | None) -> list[TracebackType]:
    out: list[TracebackType] = []
    tb = None if exc is None else exc.__traceback__
    while tb is not None:
        out.append(tb)
        tb = tb.tb_next
    return out


@pytest.mark.parametrize("bad", [-1.0, float("nan")])
def test_a_negative_or_nan_period_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="heap trim period must be >= 0 s"):
        HeapTrimmer(bad)


def test_glibc_trim_gives_freed_heap_pages_back() -> None:
    """This machine's C library is glibc (Debian): buffers that came from the heap, once freed,
    stay resident until the trim returns them."""
    trim = glibc_malloc_trim()
    assert trim is not None, "the Debian image's C library is glibc: malloc_trim must be found"

    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * 4096 / 1e6

    # below the mmap threshold: many 100 kB buffers from the heap, touched, then freed
    bufs = [np.ones(100_000, dtype=np.uint8) for _ in range(300)]
    keep = bufs[-1]   # the top of the heap stays in use, so glibc cannot shrink it on free
    del bufs
    before = rss_mb()
    assert trim() in (0, 1)
    after = rss_mb()
    assert after <= before
    assert keep.sum() == 100_000


# A fresh interpreter: an image-sized buffer raises glibc's thresholds, then a thread allocates
# and frees 12 MB of image-sized buffers and the trim runs; prints the resident growth, kB.
_THREAD_ARENA_SCRIPT = """
import ctypes, sys, threading
from hil.heap import glibc_malloc_trim, use_one_arena
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def rss_anon_kb():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("RssAnon:"))
if sys.argv[1] == "one":
    assert use_one_arena()
libc.free(libc.malloc(8 << 20))   # mmap-served and freed: the mmap threshold rises past 8 MB
base = rss_anon_kb()
def work():
    ptrs = [libc.malloc(2 << 20) for _ in range(6)]   # now from the heap (this thread's arena)
    for p in ptrs:
        ctypes.memset(p, 1, 2 << 20)
    for p in ptrs:
        libc.free(p)
t = threading.Thread(target=work)
t.start()
t.join()
trim = glibc_malloc_trim()
assert trim is not None
trim()
print(rss_anon_kb() - base)
"""


def test_one_arena_lets_the_trim_return_what_a_thread_freed() -> None:
    """The first-fault step of issue 45: a thread's arena keeps its freed top through
    ``malloc_trim``; with every thread on the main arena the trim returns it (here 12 MB, all
    of it). Without :func:`use_one_arena` the same script keeps the 12 MB when run alone (and did
    in the soak), but not in every run of the whole suite (once it kept nothing: the cause is not
    known), so only the remedy is asserted."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _THREAD_ARENA_SCRIPT, "one"], capture_output=True,
                         text=True, timeout=120, check=True)
    assert -1_000 <= int(out.stdout.strip()) < 1_000, out.stdout


def test_the_cli_puts_every_thread_on_one_arena(monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    import hil.cli

    calls: list[str] = []
    real_parser = hil.cli.build_parser
    monkeypatch.setattr(hil.cli, "use_one_arena", lambda: calls.append("arena") or True)
    monkeypatch.setattr(hil.cli, "build_parser", lambda: calls.append("parser") or real_parser())
    assert hil.cli.main([]) == hil.cli.EXIT_USAGE   # no command: the help
    assert calls == ["arena", "parser"]   # before anything else
    assert "usage: hil" in capsys.readouterr().err

