"""What ``hil run`` leaves behind: the summary, the session log with its published chain head,
the per-frame measurements the report plots, and the HTML report."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from hil.cli import main
from hil.session import read_session_log, verify_session_log
from hil.session.log import head_path


@pytest.fixture(scope="module")
def run_json(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    pytest.importorskip("matplotlib", reason="the report needs the [report] extra")
    d = tmp_path_factory.mktemp("run")
    out = d / "stdout.json"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["run", "--json", "--session-dir", str(d / "sessions")])
    out.write_text(buf.getvalue())
    doc = json.loads(buf.getvalue())
    assert isinstance(doc, dict)
    doc["_exit"] = code
    return doc


def test_summary_names_the_log_its_chain_head_and_the_report(run_json: dict[str, object]) -> None:
    assert (run_json["_exit"], run_json["final_state"]) == (0, "done")
    log = Path(str(run_json["session_log"]))
    last = log.read_bytes().rstrip(b"\n").split(b"\n")[-1]
    assert run_json["session_log_sha256"] == hashlib.sha256(last).hexdigest()
    side = json.loads(head_path(log).read_text())
    assert side["head_sha256"] == run_json["session_log_sha256"]
    rep = verify_session_log(log, expected_head_sha256=str(run_json["session_log_sha256"]))
    assert (rep.ok, rep.closed, rep.head) == (True, True, "matched")
    report = Path(str(run_json["report"]))
    assert report == log.parent / f"{log.stem}_report" / "report.html"
    html = report.read_text()
    assert "last line matches the published chain head" in html


def test_frame_records_carry_what_the_report_plots(run_json: dict[str, object]) -> None:
    from hil.report.session_data import load_session

    log = Path(str(run_json["session_log"]))
    recs = list(read_session_log(log))
    frames = [r for r in recs if r["event"] == "frame_measured"]
    assert len(frames) == run_json["frames"]
    assert all({"exposure_t_ns", "live_mm", "tcp_speed_mm_s"} <= r.keys() for r in frames)
    assert max(r["tcp_speed_mm_s"] for r in frames) > 1.0  # the approach moved the arm
    reg = next(r for r in recs if r["event"] == "registration_done")
    assert len(reg["residuals_mm"]) == len(reg["reference_optical_mm"])
    assert max(reg["residuals_mm"]) < 0.2
    data = load_session(log)
    assert len(data.robot_speed_mm_s) >= len(frames)
    assert data.marker_residuals_mm
    assert all(len(s) for s in data.marker_residuals_mm.values())
    assert len(data.registration_residuals_mm) == len(reg["residuals_mm"])


def test_no_report_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "--json", "--no-report", "--max-duration", "0.5", "--session-dir", str(tmp_path)])
    assert code == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["report"] is None
    assert len(doc["session_log_sha256"]) == 64
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".head", ".jsonl"]
