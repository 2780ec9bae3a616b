"""Session log: JSON lines, hash chain, tamper detection."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from hil.clock import ManualClock
from hil.errors import InputFileError
from hil.geometry.transform import RigidTransform
from hil.session import GENESIS_SHA256, SessionLog, SessionLogError, read_session_log, verify_session_log
from hil.session.log import head_path


def _write(path: Path, n: int = 5) -> Path:
    clock = ManualClock()
    with SessionLog(path, clock, {"config_sha256": "ab" * 32}) as log:
        for i in range(n):
            clock.advance(0.01)
            log.write("measurement", i=i, value_mm=np.float64(i * 0.5), pose=RigidTransform.identity(),
                      arr=np.arange(3), bad=float("nan"))
    return path


def test_records_carry_seq_times_and_chain(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    recs = list(read_session_log(p))
    assert [r["seq"] for r in recs] == list(range(7))
    assert recs[0]["event"] == "session_started"
    assert recs[0]["config_sha256"] == "ab" * 32
    assert recs[0]["prev_sha256"] == GENESIS_SHA256
    assert recs[-1]["event"] == "session_closed"
    assert recs[2]["t_ns"] == 20_000_000
    assert recs[1]["value_mm"] == 0.0
    assert recs[1]["arr"] == [0, 1, 2]
    assert recs[1]["bad"] is None
    assert recs[1]["pose"] == {"rotvec_rad": [0.0, 0.0, 0.0], "t_mm": [0.0, 0.0, 0.0]}
    rep = verify_session_log(p)
    assert (rep.ok, rep.records, rep.closed, rep.first_bad_line) == (True, 7, True, None)
    assert rep.session_id == recs[0]["session_id"]


def _lines(p: Path) -> list[str]:
    return p.read_text(encoding="utf-8").splitlines()


def test_a_changed_value_is_detected_at_the_next_line(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    lines = _lines(p)
    lines[3] = lines[3].replace('"i":2', '"i":9')
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line) == (False, 5)
    assert "hash chain broken" in rep.reason


def test_a_deleted_line_is_detected(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    lines = _lines(p)
    del lines[2]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert verify_session_log(p).first_bad_line == 3


def test_reordered_lines_are_detected(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    lines = _lines(p)
    lines[2], lines[3] = lines[3], lines[2]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert verify_session_log(p).first_bad_line == 3


def test_a_forged_line_with_a_recomputed_hash_still_breaks_the_sequence(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    lines = _lines(p)
    rec = json.loads(lines[2])
    lines.insert(3, json.dumps({**rec, "i": 99}, separators=(",", ":")))
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    rep = verify_session_log(p)
    assert not rep.ok
    assert rep.first_bad_line == 4


def test_a_truncated_log_is_reported_not_closed(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    lines = _lines(p)[:-1]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    rep = verify_session_log(p)
    assert (rep.ok, rep.closed) == (True, False)
    assert "not closed" in rep.reason


def test_garbage_line_is_reported(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    with open(p, "a", encoding="utf-8") as fh:
        fh.write("{not json\n")
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line) == (False, 8)
    assert rep.reason.startswith("not JSON (")
    with pytest.raises(InputFileError, match="line 8: not JSON"):
        list(read_session_log(p))


@pytest.mark.parametrize(("bad", "why"), [(b"\xfb\xff{}\n", "not UTF-8"),
                                          (b"[" * 100_000 + b"\n", "nested too deeply"),
                                          (b"1" * 5000 + b"\n", "unusable JSON")])
def test_hostile_lines_are_reported_with_the_line(tmp_path: Path, bad: bytes, why: str) -> None:
    p = _write(tmp_path / "s.jsonl")
    with open(p, "ab") as fh:
        fh.write(bad)
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line) == (False, 8)
    assert why in rep.reason
    with pytest.raises(InputFileError, match=f"line 8: .*{why}"):
        list(read_session_log(p))


def test_close_publishes_the_chain_head(tmp_path: Path) -> None:
    p = tmp_path / "s.jsonl"
    with SessionLog(p, ManualClock()) as log:
        log.write("x", a=1)
    side = json.loads(head_path(p).read_text())
    last = p.read_bytes().split(b"\n")[-2]
    assert side == {"format": "hil-session-head", "session_id": log.session_id, "records": 3,
                    "head_sha256": hashlib.sha256(last).hexdigest()}
    assert log.head_sha256 == side["head_sha256"]
    rep = verify_session_log(p)
    assert (rep.ok, rep.closed, rep.head) == (True, True, "matched")
    assert verify_session_log(p, expected_head_sha256="0" * 64).ok is False


def test_an_edited_last_line_breaks_the_published_head(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    head = verify_session_log(p)
    assert head.head == "matched"
    p.write_bytes(p.read_bytes().replace(b'"session_closed"', b'"session_closed","extra":1'))
    rep = verify_session_log(p)
    assert (rep.ok, rep.first_bad_line, rep.head) == (False, 7, "mismatch")
    assert "published chain head" in rep.reason


def test_a_cut_off_end_with_a_published_head_says_how_many_records_are_missing(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    lines = _lines(p)[:-2]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    rep = verify_session_log(p)
    assert (rep.ok, rep.closed, rep.head) == (True, False, "mismatch")
    assert "names 7 records, 5 found" in rep.reason


@pytest.mark.parametrize("text", ["garbage", '{"format": "hil-session-head"}'])
def test_an_unusable_sidecar_fails_verification(tmp_path: Path, text: str) -> None:
    p = _write(tmp_path / "s.jsonl")
    head_path(p).write_text(text)
    rep = verify_session_log(p)
    assert (rep.ok, rep.head) == (False, "mismatch")
    assert "sidecar s.jsonl.head unusable" in rep.reason


def test_reserved_keys_and_writes_after_close_are_refused(tmp_path: Path) -> None:
    log = SessionLog(tmp_path / "s.jsonl", ManualClock())
    with pytest.raises(SessionLogError, match="reserved"):
        log.write("x", seq=3)
    log.close()
    log.close()
    with pytest.raises(SessionLogError, match="closed"):
        log.write("x")


def test_an_existing_file_is_never_overwritten(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.jsonl")
    with pytest.raises(SessionLogError, match="cannot create"):
        SessionLog(p, ManualClock())


def test_unreadable_log_is_a_typed_error(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="cannot read"):
        verify_session_log(tmp_path / "missing.jsonl")
