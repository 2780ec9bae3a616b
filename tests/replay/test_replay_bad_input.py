"""``hil replay`` refuses a missing, truncated, tampered or other-version session log with one
line naming the file and what is wrong (exit 2); ``--allow-unverified`` replays a broken chain
marked UNVERIFIED in the recording."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from hil.cli import main
from hil.session.log import head_path


def _copy(log: Path, dest: Path, with_head: bool = True) -> Path:
    out = dest / log.name
    shutil.copyfile(log, out)
    if with_head:
        shutil.copyfile(head_path(log), head_path(out))
    return out


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(argv) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    lines = cap.err.splitlines()
    assert len(lines) == 1, cap.err
    return lines[0]


def test_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "nope.jsonl"
    line = _refused(["replay", str(log), "--out", str(tmp_path / "x.rrd")], capsys)
    assert line == f"hil replay: error: {log}: no such session log"
    assert not (tmp_path / "x.rrd").exists()


def test_truncated_mid_line(sim_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = _copy(sim_session, tmp_path)
    data = log.read_bytes()
    cut = data.index(b"\n", len(data) // 2) - 10  # inside a line
    log.write_bytes(data[:cut])
    n_line = data[:cut].count(b"\n") + 1
    line = _refused(["replay", str(log), "--out", str(tmp_path / "x.rrd")], capsys)
    assert line.startswith(f"hil replay: error: {log}: line {n_line}: not JSON")
    assert line.endswith("refused (--allow-unverified replays it marked unverified)")
    assert not (tmp_path / "x.rrd").exists()


def test_truncated_at_a_line_end(sim_session: Path, tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    log = _copy(sim_session, tmp_path)
    lines = log.read_bytes().splitlines(keepends=True)
    log.write_bytes(b"".join(lines[:100]))
    line = _refused(["replay", str(log), "--out", str(tmp_path / "x.rrd")], capsys)
    assert line == (f"hil replay: error: {log}: session not closed: the published chain head names "
                    f"{len(lines)} records, 100 found (the end was cut off); refused "
                    "(--allow-unverified replays it marked unverified)")


def test_tampered(sim_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = _copy(sim_session, tmp_path)
    lines = log.read_text(encoding="utf-8").splitlines(keepends=True)
    rec = json.loads(lines[49])
    rec["wall"] = "2000-01-01T00:00:00+00:00"
    lines[49] = json.dumps(rec, separators=(",", ":")) + "\n"
    log.write_text("".join(lines), encoding="utf-8")
    line = _refused(["replay", str(log), "--out", str(tmp_path / "x.rrd")], capsys)
    assert line == (f"hil replay: error: {log}: line 51: hash chain broken (a line was changed, "
                    "inserted or removed); refused (--allow-unverified replays it marked unverified)")


def test_other_version(sim_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A log of schema 2 with an intact chain (re-chained here): refused for its version."""
    log = tmp_path / "other.jsonl"
    prev = "0" * 64
    out = []
    for i, text in enumerate(sim_session.read_text(encoding="utf-8").splitlines()):
        rec = json.loads(text)
        if i == 0:
            rec["schema"] = 2
        rec["prev_sha256"] = prev
        line = json.dumps(rec, separators=(",", ":"))
        prev = hashlib.sha256(line.encode()).hexdigest()
        out.append(line + "\n")
    log.write_text("".join(out), encoding="utf-8")
    line = _refused(["replay", str(log), "--out", str(tmp_path / "x.rrd")], capsys)
    assert line == f"hil replay: error: {log}: session log schema 2, this version of hil replays schema 1"


def test_not_a_session_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "notes.jsonl"
    log.write_text("hello\n", encoding="utf-8")
    line = _refused(["replay", str(log)], capsys)
    assert line.startswith(f"hil replay: error: {log}: ")


def test_allow_unverified_marks_the_recording(sim_session: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    from rerun.chunk import RrdReader

    log = _copy(sim_session, tmp_path)
    lines = log.read_text(encoding="utf-8").splitlines(keepends=True)
    lines[49] = lines[49].replace('"seq":49', '"seq":49,"x":1')
    log.write_text("".join(lines), encoding="utf-8")
    rrd = tmp_path / "x.rrd"
    assert main(["replay", str(log), "--out", str(rrd), "--json", "--allow-unverified"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["verified"] is False
    assert doc["reason"] == "line 51: hash chain broken (a line was changed, inserted or removed)"
    assert doc["records"] == 50  # replayed up to the first broken link
    texts: dict[str, list[str]] = {}
    for chunk in RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        for col in ("TextDocument:text", "TextLog:text"):
            if col in batch.schema.names:
                texts[chunk.entity_path] = [v[0] for v in batch.column(col).to_pylist()]
    want = f"UNVERIFIED: {doc['reason']}"
    assert texts["/session/verification"] == [want]
    assert texts["/events/verification"] == [want]
    assert "events/verification" in doc["entities"]
