"""hil report: chain verdict, numbers, plots, errors on bad logs."""

from __future__ import annotations

import base64
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from hil.cli import main
from hil.errors import InputFileError
from hil.report import build_report, load_session
from tests.operator.synthetic_session import (
    FAULT_REASON,
    FRE_MM,
    LOCK_ERROR_MM,
    ROBOT_FRE_MM,
    TARGET_FALLBACKS,
    TARGET_HELD,
    TRE_MM,
    write_empty_session,
    write_full_session,
)

PLOT_KEYS = ["states", "breathing", "errors", "residuals", "body", "target", "speed"]


def _figures(page: str) -> dict[str, tuple[bool, bytes]]:
    out = {}
    for m in re.finditer(r'<figure data-plot="(\w+)" data-has-data="(true|false)">'
                         r'<img alt="[^"]*" src="data:image/png;base64,([A-Za-z0-9+/=]+)">', page):
        out[m.group(1)] = (m.group(2) == "true", base64.b64decode(m.group(3)))
    return out


def _number(page: str, key: str) -> str:
    m = re.search(rf'<tr data-key="{key}"><td>[^<]*</td><td class="num">([^<]*)</td>', page)
    assert m is not None, key
    return m.group(1)


def test_full_session_report_has_every_plot_and_number(tmp_path: Path) -> None:
    log = write_full_session(tmp_path / "session.jsonl")
    res = build_report(log, tmp_path / "out")
    page = (tmp_path / "out" / "report.html").read_text()
    assert res.html_path == tmp_path / "out" / "report.html"
    assert res.chain.ok
    assert res.chain.closed
    assert 'id="chain" data-valid="true"' in page
    figs = _figures(page)
    assert list(figs) == PLOT_KEYS
    for key, (has_data, png) in figs.items():
        assert has_data, key
        img = Image.open(io.BytesIO(png))
        assert img.format == "PNG"
        assert img.size == (1000, 280 if key != "states" else 260)
        # not a blank image: many distinct colours
        assert len(img.convert("RGB").getcolors(maxcolors=1 << 16) or []) > 20, key
    assert _number(page, "fre_mm") == f"{FRE_MM:.3f}"
    assert _number(page, "tre_expected_mm") == f"{TRE_MM:.3f}"
    assert _number(page, "robot_fre_mm") == f"{ROBOT_FRE_MM:.3f}"
    assert _number(page, "lock_error_mm") == f"{LOCK_ERROR_MM:.3f}"
    assert _number(page, "lock_truth_error_mm") == "0.520"
    assert _number(page, "faults") == "1"
    assert _number(page, "target_model_fallback_fraction") == "0.150"
    assert _number(page, "target_model_held_fraction") == "0.100"
    assert "fell back on 3 of 20 pairs, held at a bound on 2" in page
    assert _number(page, "final_state") == "done"
    assert FAULT_REASON in page
    nums = {n.key: n.value for n in res.numbers}
    comp = 1.0 + 0.1 * np.arange(20)
    assert nums["comp_error_rms_mm"] == pytest.approx(float(np.sqrt(np.mean(comp**2))), abs=1e-12)
    assert nums["comp_error_max_mm"] == pytest.approx(2.9, abs=1e-12)
    assert nums["gate_open_fraction"] == pytest.approx(1 / 25)
    assert nums["time_to_lock_s"] == pytest.approx(7.7, abs=1e-6)
    assert nums["duration_s"] == pytest.approx(8.4, abs=1e-6)
    expect = {"idle": 0.1, "register": 1.0, "plan": 0.1, "approach": 2.1, "gate": 2.5,
              "compensate": 2.0, "lock": 0.4, "fault": 0.2, "done": 0.0}
    assert list(res.time_in_state_s) == list(expect)
    for s, v in expect.items():
        assert res.time_in_state_s[s] == pytest.approx(v, abs=1e-6), s
        m = re.search(rf'<tr data-key="{s}"><td>.*?</td><td class="num">([0-9.]+)</td>', page)
        assert m is not None
        assert float(m.group(1)) == pytest.approx(v, abs=1e-3)
    assert res.faults == ((pytest.approx(7.9, abs=1e-6), FAULT_REASON),)


def test_session_data_series(tmp_path: Path) -> None:
    data = load_session(write_full_session(tmp_path / "s.jsonl"))
    assert data.robot_speed_kind == "measured"
    assert len(data.robot_speed_mm_s) == 20
    assert sorted(data.marker_residuals_mm) == [0, 1, 2, 3, 4]
    # live = reference + common shift, marker 4 moved 0.2 mm: the rigid fit leaves residuals,
    # largest on marker 4
    last = {i: s.y[-1] for i, s in data.marker_residuals_mm.items()}
    assert max(last, key=lambda i: last[i]) == 4
    assert 0.05 < last[4] < 0.2
    assert len(data.breathing_mm) == 25 + 20 + 2
    assert data.gate_tolerance_mm == 1.5
    open_spans = data.gate_open_intervals()
    assert open_spans[0][0] == pytest.approx(5.7, abs=1e-6)  # the open gate sample
    closed = data.gate_closed_intervals()
    assert closed == [(pytest.approx(3.2, abs=1e-6), pytest.approx(5.7, abs=1e-6))]
    # the body's state: 25 gate samples and the first lock's (the second lock logged none)
    assert data.shape_mm.y == pytest.approx([0.1 * k for k in range(25)] + [0.25], abs=1e-12)
    assert sorted(data.marker_deviations_mm) == [0, 1, 2, 3, 4]
    assert len(data.marker_deviations_mm[2]) == 1            # unseen in the gate (null), seen at lock
    assert len(data.marker_deviations_mm[4]) == 26
    assert data.marker_deviations_mm[4].y[-1] == 0.5
    assert data.change_fre_mm.y == pytest.approx([0.05 * k for k in range(20)], abs=1e-12)
    # the surrogate target model: every compensation pair, three of which fell back
    assert len(data.target_turn_deg) == 20
    assert data.target_shift_mm.y == pytest.approx([0.2 * k for k in range(20)], abs=1e-12)
    assert [why for _, why in data.target_fallbacks] == list(TARGET_FALLBACKS.values())
    assert data.target_model_fallback_fraction() == pytest.approx(3 / 20)
    assert data.target_held == [(pytest.approx(t), why) for t, why in zip(
        [data.target_turn_deg.t_s[k] for k in TARGET_HELD], TARGET_HELD.values(), strict=True)]
    assert data.target_model_held_fraction() == pytest.approx(2 / 20)
    assert data.target_sensor_fraction() is None          # no target sensor: no target_source logged


def test_empty_session_plots_say_no_data(tmp_path: Path) -> None:
    res = build_report(write_empty_session(tmp_path / "e.jsonl"), tmp_path / "out")
    page = res.html_path.read_text()
    figs = _figures(page)
    assert list(figs) == PLOT_KEYS
    assert {k: v[0] for k, v in figs.items()} == {"states": True, "breathing": False, "errors": False,
                                                  "residuals": False, "body": False,
                                                  "target": False, "speed": False}
    assert all(len(png) > 1000 for _, png in figs.values())
    assert _number(page, "fre_mm") == "n/a"
    assert _number(page, "target_model_fallback_fraction") == "n/a"
    assert _number(page, "target_model_held_fraction") == "n/a"
    assert res.chain.ok


def test_tampered_log_reports_broken_line_and_exit_1(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = write_full_session(tmp_path / "s.jsonl")
    lines = log.read_text().splitlines()
    n = next(i for i, ln in enumerate(lines) if '"registration_done"' in ln)
    lines[n] = lines[n].replace(f'"fre_mm":{FRE_MM}', '"fre_mm":0.1')
    log.write_text("\n".join(lines) + "\n")
    code = main(["report", str(log), "--out", str(tmp_path / "r")])
    out = json.loads(capsys.readouterr().out)
    assert code == 1
    # the line after the changed one no longer links to it
    assert out["chain"] == {"valid": False, "records": n + 1, "first_bad_line": n + 2,
                            "reason": "hash chain broken (a line was changed, inserted or removed)",
                            "closed": False, "session_id": out["chain"]["session_id"], "head": "absent"}
    page = (tmp_path / "r" / "report.html").read_text()
    assert f"broken at line {n + 2}" in page
    assert 'data-valid="false"' in page


def test_cli_valid_log_json_and_progress(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = write_full_session(tmp_path / "s.jsonl")
    code = main(["report", str(log)])
    cap = capsys.readouterr()
    out = json.loads(cap.out)
    assert code == 0
    assert out["report"] == str(tmp_path / "s_report" / "report.html")
    assert out["chain"]["valid"] is True
    assert out["chain"]["head"] == "matched"  # the writer published the chain head on close
    assert out["numbers"]["fre_mm"] == FRE_MM
    assert out["plots"] == dict.fromkeys(PLOT_KEYS, "ok")
    assert "hil report: plot 7/7: speed" in cap.err


@pytest.mark.parametrize(("content", "line", "what"), [
    ('{"t_ns":0,"event":"session_started"}\nnot json at all\n', 2, "not JSON"),
    ("[1, 2]\n", 1, "not a JSON object"),
    ('{"seq":0,"event":"x"}\n', 1, "no integer 't_ns'"),
    ('{"seq":0,"t_ns":5}\n', 1, "no 'event' name"),
    ('{"t_ns":0,"event":"session_started"}\n{"t_ns":1,"event":"registration_done","fre_mm":"big"}\n',
     2, "field 'fre_mm' of 'registration_done' is not a number"),
    ('{"t_ns":0,"event":"session_started"}\n{"t_ns":1,"event":"gate_measured","open":1}\n',
     2, "field 'open' of 'gate_measured' is not true/false"),
])
def test_garbage_log_is_a_typed_error_naming_file_and_line(
        tmp_path: Path, content: str, line: int, what: str) -> None:
    log = tmp_path / "bad.jsonl"
    log.write_text(content)
    with pytest.raises(InputFileError) as ei:
        build_report(log, tmp_path / "out")
    assert ei.value.path == str(log)
    assert f"line {line}" in ei.value.reason
    assert what in ei.value.reason


def test_cli_garbage_and_missing_file_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "bad.jsonl"
    log.write_bytes(b"\x00\x01garbage\n")
    assert main(["report", str(log)]) == 2
    err = capsys.readouterr().err
    assert f"hil report: error: {log}: line 1: not JSON" in err
    assert main(["report", str(tmp_path / "nope.jsonl")]) == 2
    assert "cannot read session log" in capsys.readouterr().err


def test_empty_file_is_a_typed_error(tmp_path: Path) -> None:
    log = tmp_path / "empty.jsonl"
    log.write_text("")
    with pytest.raises(InputFileError, match="empty session log"):
        build_report(log, tmp_path / "out")
