"""`hil traces check`: text and --json on a written file and on a shared InterACT trace; bad input ->
exit 2 and one stderr line (in-process, hil.cli.main)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.cli import main
from tests.io.shared_data import shared_path


def _csv(tmp_path: Path) -> Path:
    rows = ["time_s,chest_x_mm,chest_y_mm,chest_z_mm,belly_x_mm,belly_y_mm,belly_z_mm"]
    rows += [f"{0.25 * i},{0.5 * i},0,0,0,0,{-i}" for i in range(41)]
    p = tmp_path / "rec.csv"
    p.write_text("\n".join(rows) + "\n")
    (tmp_path / "rec.csv.points.json").write_text('{"chest": [10, 20], "belly": [-5, -60]}')
    return p


def test_check_json_on_written_points_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = _csv(tmp_path)
    assert main(["traces", "check", str(p), "--json"]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    s = json.loads(out)
    assert s == {
        "path": str(p), "format": "points-csv", "samples": 41, "time_start_s": 0.0, "duration_s": 10.0,
        "rate_hz": 4.0, "points": 2, "point_names": ["chest", "belly"], "amplitude_mm": [20.0, 40.0],
        "amplitude_units": "mm", "surrogate_amplitude": None, "rotation_amplitude_deg": None,
        "point_places_mm": {"chest": [10.0, 20.0], "belly": [-5.0, -60.0]}, "gaps": [],
        "units": {"time": "s", "position": "mm",
                  "axes": "image frame: x = patient's left, y = superior, z = anterior",
                  "places": "sidecar rec.csv.points.json"},
    }


def test_check_text_on_written_points_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = _csv(tmp_path)
    assert main(["traces", "check", str(p)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert out.splitlines() == [
        f"file        {p}",
        "format      points-csv",
        "samples     41",
        "duration_s  10 (from 0 s)",
        "rate_hz     4",
        "points      2",
        "amplitude   chest: 20.000 mm peak to peak  at skin x, y = 10, 20 mm",
        "            belly: 40.000 mm peak to peak  at skin x, y = -5, -60 mm",
        "gaps        none",
        "units       time: s",
        "            position: mm",
        "            axes: image frame: x = patient's left, y = superior, z = anterior",
        "            places: sidecar rec.csv.points.json",
    ]


def test_check_shared_6dof_trace(capsys: pytest.CaptureFixture[str]) -> None:
    path = shared_path("respiration", "interact", "6dof", "Liver", "Liver_Trace 2.txt")
    assert main(["traces", "check", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["format"], s["samples"], s["duration_s"], s["rate_hz"], s["points"]) == (
        "6dof", 6370, 1273.8, 5.0, 1)
    assert s["amplitude_mm"] == [pytest.approx(29.979, abs=1e-3)]
    assert s["gaps"] == []
    assert s["units"]["position"] == "mm"
    assert s["units"]["rotation"] == "deg"
    assert main(["traces", "check", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1:7] == ["format      6dof", "samples     6370", "duration_s  1273.8 (from 0 s)",
                          "rate_hz     5", "points      1", "amplitude   target: 29.979 mm peak to peak"]


def test_check_shared_paired_directory(capsys: pytest.CaptureFixture[str]) -> None:
    path = shared_path("respiration", "interact", "paired", "LIGHT_SABR_Lung_High_Motion")
    assert main(["traces", "check", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["format"], s["samples"], s["points"]) == ("paired", 1500, 1)
    assert s["amplitude_mm"] == [21.04]
    assert s["surrogate_amplitude"] == pytest.approx(9.6856, abs=1e-4)


def test_bad_file_exits_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "bad.txt"
    p.write_text("0 1\n0.2 nan\n")
    assert main(["traces", "check", str(p)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == f"hil traces: error: {p}:2: column 2: not a finite number: 'nan'\n"
    missing = tmp_path / "none.csv"
    assert main(["traces", "check", str(missing), "--json"]) == 2
    assert capsys.readouterr().err == f"hil traces: error: {missing}: no such file or directory\n"


def test_format_option_is_honoured(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "s.txt"
    p.write_text("\n".join(f"{0.2 * i:.1f} {i % 5}" for i in range(40)))
    assert main(["traces", "check", str(p), "--format", "6dof"]) == 2
    assert capsys.readouterr().err == f"hil traces: error: {p}:1: expected 7 columns, found 2\n"
    assert main(["traces", "check", str(p), "--format", "surrogate", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["format"], s["amplitude_mm"], s["amplitude_units"]) == (
        "surrogate", [4.0], "arbitrary (surrogate units)")


def test_usage_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["traces"], ["traces", "check", "x", "--format", "xml"]):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2
    capsys.readouterr()
