"""Session logs from outside (a copied, damaged or forged file) fed to the verifier, the reader and
the report's loader: a verdict, or InputFileError naming the file and line; never a crash, and a
changed byte never verifies as intact."""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.errors import InputFileError
from hil.report.session_data import load_session
from hil.session.log import read_session_log, verify_session_log

from .session_fixture import write_session
from .strategies import mutated_bytes, outcome


@functools.cache
def _good_log() -> bytes:
    with tempfile.TemporaryDirectory() as d:
        return write_session(Path(d) / "s.jsonl").read_bytes()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("sess_fuzz")


def test_fixture_log_verifies(workdir: Path) -> None:
    good_log = _good_log()
    p = workdir / "good.jsonl"
    p.write_bytes(good_log)
    rep = verify_session_log(p)
    assert (rep.ok, rep.closed, rep.records) == (True, True, good_log.count(b"\n"))


@settings(max_examples=300)
@given(st.data())
def test_damaged_log_never_verifies(workdir: Path, data: st.DataObject) -> None:
    good_log = _good_log()
    raw = data.draw(mutated_bytes(good_log, max_edits=3))
    p = workdir / "damaged.jsonl"
    p.write_bytes(raw)
    rep = outcome(lambda: verify_session_log(p), (InputFileError,))
    if isinstance(rep, InputFileError):  # not UTF-8 at all
        assert rep.path == str(p)
        return
    if raw == good_log:
        assert rep.ok
        return
    clean_cut = (good_log.startswith(raw.rstrip(b"\n")) and raw.endswith(b"\n")) or good_log.startswith(raw)
    if clean_cut and rep.ok:
        # a clean cut at a line end is the one damage a chain cannot see from inside: it reads
        # as a session that ended abruptly (not closed) -- unless only the final newline went
        assert not rep.closed or raw.rstrip(b"\n") == good_log.rstrip(b"\n")
        return
    assert not rep.ok or not rep.closed, "a damaged log verified as complete"
    if not rep.ok:
        assert rep.first_bad_line is None or 1 <= rep.first_bad_line <= raw.count(b"\n") + 1
        assert rep.reason


@settings(max_examples=150)
@given(st.data())
def test_damaged_log_reader_and_report_loader(workdir: Path, data: st.DataObject) -> None:
    # ASCII damage only: non-UTF-8 bytes are a known reader defect (test_known_bugs.py)
    raw = bytes(b & 0x7F for b in data.draw(mutated_bytes(_good_log(), max_edits=3)))
    p = workdir / "damaged_read.jsonl"
    p.write_bytes(raw)
    outcome(lambda: list(read_session_log(p)), (InputFileError,))
    res = outcome(lambda: load_session(p), (InputFileError,))
    if isinstance(res, InputFileError):
        assert res.path == str(p)


@settings(max_examples=150)
@given(st.binary(max_size=300))
def test_random_bytes_as_session_log(workdir: Path, raw: bytes) -> None:
    p = workdir / "random.jsonl"
    p.write_bytes(raw)
    rep = outcome(lambda: verify_session_log(p), (InputFileError,))
    if not isinstance(rep, InputFileError):
        assert not (rep.ok and rep.closed)
    p.write_bytes(bytes(b & 0x7F for b in raw))
    outcome(lambda: load_session(p), (InputFileError,))


@settings(max_examples=8)
@given(st.data())
def test_damaged_log_through_hil_report(workdir: Path, data: st.DataObject) -> None:
    """The whole report (chain verdict, numbers, plots, HTML) on a damaged log: a report that says
    the chain is broken, or InputFileError naming the file."""
    pytest.importorskip("matplotlib", reason="hil report needs the [report] extra")
    from hil.report.build import build_report

    raw = bytes(b & 0x7F for b in data.draw(mutated_bytes(_good_log(), max_edits=2)))
    p = workdir / "damaged_report.jsonl"
    p.write_bytes(raw)
    res = outcome(lambda: build_report(p, workdir / "report"), (InputFileError,))
    if isinstance(res, InputFileError):
        assert res.path in (str(p), str(workdir / "report"))
        return
    if raw != _good_log():
        assert not (res.chain.ok and res.chain.closed)
    assert res.html_path.is_file()
