"""The soak's memory breakdown (hil/soak/heapmap.py): smaps parsing by kind and by file, the live
reading, the per-minute series and the files whose pages grew."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.soak.heapmap import (
    HeapBreakdown,
    file_growth,
    parse_smaps_file_rss_kb,
    parse_smaps_rss_kb,
    read_heap_breakdown,
)
from hil.soak.sampler import rss_mb
from hil.soak.soak import heap_by_minute

SMAPS = """\
55d0c0a00000-55d0c0a21000 r--p 00000000 08:01 1234                       /usr/bin/python3.11
Size:                132 kB
Rss:                 120 kB
VmFlags: rd mr mw me sd
55d0c2000000-55d0c4000000 rw-p 00000000 00:00 0                          [heap]
Rss:                30000 kB
Pss:                30000 kB
7f0000000000-7f0000100000 rw-p 00000000 00:00 0
Rss:                 1024 kB
7f0000200000-7f0000300000 rw-s 00000000 00:19 77                         /dev/shm/hil-servo (deleted)
Rss:                   64 kB
7ffd00000000-7ffd00021000 rw-p 00000000 00:00 0                          [stack]
Rss:                   40 kB
"""


def test_smaps_rss_is_summed_by_kind_of_mapping() -> None:
    assert parse_smaps_rss_kb(SMAPS) == {"heap": 30000, "anon": 1064, "file": 184}


def test_smaps_rss_is_summed_by_file() -> None:
    two_maps = SMAPS + ("55d0c0b00000-55d0c0c00000 r-xp 00021000 08:01 1234                       "
                        "/usr/bin/python3.11\nRss:                 900 kB\n")
    assert parse_smaps_file_rss_kb(two_maps) == {"/usr/bin/python3.11": 1020,
                                                 "/dev/shm/hil-servo (deleted)": 64}


def _files(**kb: int) -> HeapBreakdown:
    files = tuple(sorted((f"/lib/{k}.so", v) for k, v in kb.items()))
    return HeapBreakdown(1.0, 1.0, 0.0, 1, 1.0, 1.0, 1.0, files)


def test_file_growth_names_the_files_paged_in_after_the_warm_up() -> None:
    readings = [(10.0, _files(a=100, b=50)),            # before the warm-up's end: not the base
                (40.0, _files(a=200, b=50)),            # the base
                (100.0, _files(a=200, b=50, c=30)),
                (160.0, _files(a=900, b=120, c=30)),    # a +700, b +70 (first here); c +30 < 64
                (220.0, _files(a=900, b=120, c=30)),
                (230.0, HeapBreakdown(1.0, 1.0, 0.0, 1, None, None, None))]   # smaps unreadable
    assert file_growth(readings, t_from=30.0, t0=10.0) == [
        {"file": "/lib/a.so", "kb": 700, "first_grew_min": 2.5},
        {"file": "/lib/b.so", "kb": 70, "first_grew_min": 2.5}]
    assert file_growth(readings, t_from=30.0, t0=10.0, min_kb=1, top=1) == [
        {"file": "/lib/a.so", "kb": 700, "first_grew_min": 2.5}]
    assert file_growth(readings[:2], t_from=30.0, t0=10.0) == []


def test_a_malformed_rss_line_is_named() -> None:
    with pytest.raises(ValueError, match="unreadable Rss line 'Rss: lots'"):
        parse_smaps_rss_kb(SMAPS + "Rss: lots\n")


def test_the_live_reading_sees_a_held_buffer_in_the_c_heap() -> None:
    """8 MB held through malloc shows in glibc's in-use figure. Where its pages land (a fresh
    ``mmap``, the brk heap, or free heap pages that were already resident) depends on glibc's
    dynamic thresholds and the process's history, so the resident figures are checked against
    the kernel's own total instead: the kinds add up to the process's RSS."""
    before = read_heap_breakdown()
    held = np.ones(8 * 2**20 // 8)
    during = read_heap_breakdown()
    assert before.c_in_use_mb is not None
    assert during.c_in_use_mb is not None
    assert during.c_in_use_mb - before.c_in_use_mb >= 7.9
    assert during.python_blocks > 0
    parts = (during.heap_rss_mb, during.anon_rss_mb, during.file_rss_mb)
    assert all(p is not None and p >= 0.0 for p in parts)
    assert sum(p for p in parts if p is not None) == pytest.approx(rss_mb(), abs=2.0)
    assert during.file_rss_kb_by_path is not None
    by_file_mb = sum(kb for _, kb in during.file_rss_kb_by_path) / 1024.0
    assert by_file_mb == pytest.approx(during.file_rss_mb, abs=1e-9)
    del held


def test_unreadable_smaps_leaves_those_figures_none(tmp_path: Path) -> None:
    b = read_heap_breakdown(str(tmp_path / "absent"))
    assert (b.heap_rss_mb, b.anon_rss_mb, b.file_rss_mb, b.file_rss_kb_by_path) == (None, None, None, None)
    assert b.c_in_use_mb is not None                # glibc on this machine


def test_heap_by_minute_counts_from_compensation() -> None:
    b = HeapBreakdown(1.234, 2.0, 0.5, 7, 3.0, 4.0, 5.0)
    out = heap_by_minute([(100.0, b), (160.0, b)], t_comp=130.0)
    assert out == [{"t_min": -0.5, "c_in_use_mb": 1.23, "c_free_mb": 2.0, "c_mmapped_mb": 0.5,
                    "python_blocks": 7, "heap_rss_mb": 3.0, "anon_rss_mb": 4.0, "file_rss_mb": 5.0},
                   {"t_min": 0.5, "c_in_use_mb": 1.23, "c_free_mb": 2.0, "c_mmapped_mb": 0.5,
                    "python_blocks": 7, "heap_rss_mb": 3.0, "anon_rss_mb": 4.0, "file_rss_mb": 5.0}]
    assert heap_by_minute([], None) == []
