"""Session logs are append-only and tamper-evident: editing, deleting, inserting or reordering any
line is caught by the verifier, which names the first bad line; ``hil report`` says so."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.clock import ManualClock
from hil.session.log import SessionLog, SessionLogError, verify_session_log
from tests.fuzz.session_fixture import write_session


@pytest.fixture
def log(tmp_path: Path) -> tuple[Path, list[str]]:
    p = write_session(tmp_path / "session.jsonl")
    return p, p.read_text().splitlines()


def _write(p: Path, lines: list[str]) -> None:
    p.write_text("".join(ln + "\n" for ln in lines))


def test_intact_log_verifies(log: tuple[Path, list[str]]) -> None:
    p, lines = log
    rep = verify_session_log(p)
    assert (rep.ok, rep.closed, rep.records, rep.first_bad_line) == (True, True, len(lines), None)


@pytest.mark.parametrize("n", [1, 2, 10, 20])  # 1-based line to edit
def test_edited_line_is_named(log: tuple[Path, list[str]], n: int) -> None:
    p, lines = log
    rec = json.loads(lines[n - 1])
    rec["t_ns"] = rec["t_ns"] + 1  # a one-nanosecond forgery, same key order
    lines[n - 1] = json.dumps(rec, separators=(",", ":"))
    _write(p, lines)
    rep = verify_session_log(p)
    assert not rep.ok
    assert rep.first_bad_line == n + 1  # the next record's link to the edited line breaks
    assert "hash chain broken" in rep.reason


def test_edit_of_the_last_lines_event_reads_as_not_closed(log: tuple[Path, list[str]]) -> None:
    p, lines = log
    rec = json.loads(lines[-1])
    rec["event"] = "something_else"
    lines[-1] = json.dumps(rec, separators=(",", ":"))
    _write(p, lines)
    assert not verify_session_log(p).closed


def test_edit_of_the_last_lines_data_is_caught(log: tuple[Path, list[str]]) -> None:
    """No record follows the last one, so its edit breaks no link: the chain head published
    outside the file on close (sidecar ``<log>.head``, run summary) catches it."""
    p, lines = log
    rec = json.loads(lines[-1])
    rec["final_state"] = "fault"
    lines[-1] = json.dumps(rec, separators=(",", ":"))
    _write(p, lines)
    assert not verify_session_log(p).ok


@pytest.mark.parametrize("n", [2, 5, 15])
def test_deleted_line_is_named(log: tuple[Path, list[str]], n: int) -> None:
    p, lines = log
    del lines[n - 1]
    _write(p, lines)
    rep = verify_session_log(p)
    assert not rep.ok
    assert rep.first_bad_line == n  # the line that now sits where the deleted one was


def test_deleted_first_line_is_named(log: tuple[Path, list[str]]) -> None:
    p, lines = log
    _write(p, lines[1:])
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line) == (False, 1)


def test_deleted_tail_reads_as_not_closed(log: tuple[Path, list[str]]) -> None:
    """Cutting records off the end keeps every remaining link intact: the verifier reports a
    session that did not close (the audit sees it is incomplete)."""
    p, lines = log
    _write(p, lines[:-3])
    rep = verify_session_log(p)
    assert (rep.ok, rep.closed) == (True, False)
    assert "not closed" in rep.reason


@pytest.mark.parametrize("n", [2, 7, 30])
def test_inserted_line_is_named(log: tuple[Path, list[str]], n: int) -> None:
    p, lines = log
    forged = json.loads(lines[n - 2])  # a copy of the previous record, re-linked and re-numbered
    forged["event"] = "operator_command"
    lines.insert(n - 1, json.dumps(forged, separators=(",", ":")))
    _write(p, lines)
    rep = verify_session_log(p)
    assert not rep.ok
    assert rep.first_bad_line in (n, n + 1)
    assert rep.first_bad_line == n  # its prev_sha256 is the one of line n-2, not n-1


def test_inserted_correctly_linked_line_is_named_by_the_next(log: tuple[Path, list[str]]) -> None:
    """A forger who computes the right prev_sha256 for the inserted line still breaks the next link."""
    import hashlib

    p, lines = log
    n = 6
    forged = json.loads(lines[n - 2])
    forged["seq"] = n - 1
    forged["event"] = "operator_command"
    forged["prev_sha256"] = hashlib.sha256(lines[n - 2].encode()).hexdigest()
    lines.insert(n - 1, json.dumps(forged, separators=(",", ":")))
    _write(p, lines)
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line) == (False, n + 1)


@pytest.mark.parametrize(("a", "b"), [(2, 3), (5, 9), (10, 11)])
def test_reordered_lines_are_named(log: tuple[Path, list[str]], a: int, b: int) -> None:
    p, lines = log
    lines[a - 1], lines[b - 1] = lines[b - 1], lines[a - 1]
    _write(p, lines)
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line) == (False, a)


def test_blank_line_inserted_is_named(log: tuple[Path, list[str]]) -> None:
    p, lines = log
    lines.insert(4, "")
    _write(p, lines)
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line) == (False, 5)


def test_writer_refuses_to_append_to_an_existing_log(log: tuple[Path, list[str]]) -> None:
    """Append-only: a new session never reopens (or truncates) an existing file."""
    p, lines = log
    with pytest.raises(SessionLogError, match="cannot create"):
        SessionLog(p, ManualClock())
    assert p.read_text().splitlines() == lines


def test_hil_report_says_the_chain_is_broken(log: tuple[Path, list[str]], tmp_path: Path) -> None:
    pytest.importorskip("matplotlib", reason="hil report needs the [report] extra")
    from hil.report.build import build_report, chain_status

    p, lines = log
    del lines[4]
    _write(p, lines)
    res = build_report(p, tmp_path / "report")
    assert not res.chain.ok
    assert (
        chain_status(res.chain)
        == "broken at line 5: hash chain broken (a line was changed, inserted or removed)"
    )
    assert "broken at line 5" in res.html_path.read_text()
