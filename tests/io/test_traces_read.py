"""hil.io.traces: every format on small files the tests write, auto-detection, resampling, summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hil.errors import HilError, InputFileError
from hil.io.traces import (
    Trace,
    TraceError,
    detect_format,
    principal_amplitude,
    read_trace,
    resample,
    trace_summary,
)


def _write(path: Path, text: str) -> str:
    path.write_text(text, encoding="utf-8")
    return str(path)


def _points_csv(tmp_path: Path, n: int = 11, name: str = "rec.csv") -> str:
    rows = ["time_s,chest_x_mm,chest_y_mm,chest_z_mm,belly-2_x_mm,belly-2_y_mm,belly-2_z_mm"]
    for i in range(n):
        t = 0.5 * i
        rows.append(f"{t},{1.0 + i},{2.0},{3.0 - 2 * i},{-1.0},{0.25 * i},{10.0}")
    return _write(tmp_path / name, "\n".join(rows) + "\n")


def _surrogate(tmp_path: Path, n: int = 30, sep: str = " ") -> str:
    text = "\n".join(f"{0.2 * i:.1f}{sep}{np.sin(0.2 * i):.6f}" for i in range(n))
    return _write(tmp_path / "s_resp.txt", text)  # no trailing newline, as some InterACT files


def _sixdof(tmp_path: Path, n: int = 30, name: str = "t6.txt") -> str:
    rows = [f"{0.2 * i:.1f} {0.1 * i} {-0.5 * i} {0.2} {0.01 * i} {-0.02 * i} 0.5" for i in range(n)]
    return _write(tmp_path / name, "\n".join(rows) + "\n")


def test_points_csv_reads_points_in_image_frame(tmp_path: Path) -> None:
    tr = read_trace(_points_csv(tmp_path))
    assert tr.format == "points-csv"
    assert list(tr.points_mm) == ["chest", "belly-2"]
    np.testing.assert_array_equal(tr.time_s, 0.5 * np.arange(11))
    np.testing.assert_array_equal(tr.points_mm["chest"][3], [4.0, 2.0, -3.0])
    np.testing.assert_array_equal(tr.points_mm["belly-2"][4], [-1.0, 1.0, 10.0])
    assert tr.point_places_mm is None
    assert tr.surrogate is None
    assert tr.target_mm is None
    assert tr.target_rotation_deg is None
    assert tr.units["time"] == "s"
    assert tr.units["position"] == "mm"
    assert tr.duration_s == 5.0
    assert tr.rate_hz == 2.0
    assert not tr.time_s.flags.writeable
    assert not tr.points_mm["chest"].flags.writeable


def test_points_csv_columns_in_any_order_and_comments(tmp_path: Path) -> None:
    rows = ["# my recording", "time_s, p_z_mm, p_x_mm, p_y_mm", ""]
    rows += [f"{i}, {i * 3}, {i}, {i * 2}" for i in range(12)]
    tr = read_trace(_write(tmp_path / "r.csv", "\n".join(rows)))
    np.testing.assert_array_equal(tr.points_mm["p"][2], [2.0, 4.0, 6.0])


def test_points_csv_sidecar_places(tmp_path: Path) -> None:
    path = _points_csv(tmp_path)
    (tmp_path / "rec.csv.points.json").write_text(json.dumps({"chest": [10, -20.5], "belly-2": [0, 0]}))
    tr = read_trace(path)
    assert tr.point_places_mm == {"chest": (10.0, -20.5), "belly-2": (0.0, 0.0)}
    assert tr.units["places"] == "sidecar rec.csv.points.json"


def test_surrogate_whitespace_and_comma(tmp_path: Path) -> None:
    for sep in (" ", "\t", ",", ", "):
        tr = read_trace(_surrogate(tmp_path, sep=sep))
        assert tr.format == "surrogate"
        assert tr.time_s.shape == (30,)
        assert tr.surrogate is not None
        assert tr.surrogate[5] == pytest.approx(np.sin(1.0), abs=1e-6)
        assert tr.points_mm == {}
        assert tr.target_mm is None
        assert tr.units == {"time": "s", "surrogate": "arbitrary"}
        assert tr.rate_hz == pytest.approx(5.0)


def test_6dof_columns_map_to_image_axes(tmp_path: Path) -> None:
    tr = read_trace(_sixdof(tmp_path))
    assert tr.format == "6dof"
    assert tr.target_mm is not None
    assert tr.target_rotation_deg is not None
    np.testing.assert_allclose(tr.target_mm[4], [0.4, -2.0, 0.2])
    np.testing.assert_allclose(tr.target_rotation_deg[4], [0.04, -0.08, 0.5])
    assert tr.units["rotation"] == "deg"
    assert tr.units["position"] == "mm"
    assert tr.surrogate is None


def _paired_dir(tmp_path: Path, n_tumour: int = 30, n_resp: int = 30, col: int = 3) -> Path:
    d = tmp_path / "pair"
    d.mkdir()
    rows = []
    for i in range(n_tumour):
        vals = ["0"] * 6
        vals[col - 1] = f"{0.5 * i}"
        rows.append(f"{0.2 * i:.1f} " + " ".join(vals))
    (d / "1.Trace SI.txt").write_text("\n".join(rows))
    (d / "1.Trace_resp.txt").write_text("\n".join(f"{0.2 * i:.1f} {-i}" for i in range(n_resp)))
    return d


def test_paired_single_si_column_goes_to_image_y(tmp_path: Path) -> None:
    tr = read_trace(_paired_dir(tmp_path))
    assert tr.format == "paired"
    assert tr.target_mm is not None
    assert tr.surrogate is not None
    np.testing.assert_allclose(tr.target_mm[6], [0.0, 3.0, 0.0])
    assert tr.surrogate[6] == -6.0
    assert tr.target_rotation_deg is None
    assert tr.units["tumour_file"] == "1.Trace SI.txt"
    assert tr.units["surrogate_file"] == "1.Trace_resp.txt"
    assert tr.units["axes"].startswith("superior-inferior motion in column 4 of 7 -> image y")
    assert "note" not in tr.units


def test_paired_common_span_drops_extra_samples(tmp_path: Path) -> None:
    tr = read_trace(_paired_dir(tmp_path, n_tumour=31, n_resp=30))
    assert tr.time_s.size == 30
    assert tr.units["note"] == "common span 0-5.8 s: dropped 1 sample(s) of 1.Trace SI.txt"


def test_paired_3d_tumour_reads_as_6dof_columns(tmp_path: Path) -> None:
    d = _paired_dir(tmp_path)
    (d / "1.Trace SI.txt").write_text("\n".join(f"{0.2 * i:.1f} 1 {i} 2 0 0 0.5" for i in range(30)))
    tr = read_trace(d)
    assert tr.target_mm is not None
    assert tr.target_rotation_deg is not None
    np.testing.assert_allclose(tr.target_mm[3], [1.0, 3.0, 2.0])
    assert tr.units["rotation"] == "deg"


def test_auto_detection(tmp_path: Path) -> None:
    assert detect_format(_points_csv(tmp_path)) == "points-csv"
    assert detect_format(_surrogate(tmp_path)) == "surrogate"
    assert detect_format(_sixdof(tmp_path)) == "6dof"
    assert detect_format(_paired_dir(tmp_path)) == "paired"


def test_explicit_format_overrides_detection(tmp_path: Path) -> None:
    path = _sixdof(tmp_path)
    with pytest.raises(TraceError) as e:
        read_trace(path, "surrogate")
    assert str(e.value) == f"{path}:1: expected 2 columns, found 7"
    assert read_trace(path, "6dof").format == "6dof"


def test_trace_error_is_an_input_file_error() -> None:
    err = TraceError("f.txt", "bad", 3)
    assert isinstance(err, InputFileError)
    assert isinstance(err, HilError)
    assert (err.path, err.line, err.reason, str(err)) == ("f.txt", 3, "bad", "f.txt:3: bad")
    err2 = TraceError("f.txt", "bad")
    assert (err2.line, str(err2)) == (None, "f.txt: bad")


def test_gaps(tmp_path: Path) -> None:
    times = [0.0, 0.2, 0.4, 0.6, 1.4, 1.6, 1.8, 2.0, 2.2, 2.4, 5.0, 5.2]
    path = _write(tmp_path / "g.txt", "\n".join(f"{t} 1" for t in times))
    tr = read_trace(path, min_duration_s=1.0)
    assert tr.gaps() == [(pytest.approx(0.6), pytest.approx(0.8)), (pytest.approx(2.4), pytest.approx(2.6))]
    assert tr.gaps(factor=5.0) == [(pytest.approx(2.4), pytest.approx(2.6))]
    with pytest.raises(ValueError, match="gap factor"):
        tr.gaps(1.0)


def test_resample_linear_and_records_method(tmp_path: Path) -> None:
    tr = read_trace(_sixdof(tmp_path))
    up = resample(tr, 10.0)
    assert up.time_s.size == 59
    np.testing.assert_allclose(up.time_s[:3], [0.0, 0.1, 0.2])
    assert up.target_mm is not None
    assert up.target_rotation_deg is not None
    np.testing.assert_allclose(up.target_mm[1], [0.05, -0.25, 0.2])
    assert up.units["resampled"] == "linear interpolation to 10 Hz from 5 Hz"
    assert up.rate_hz == pytest.approx(10.0)
    assert tr.units.get("resampled") is None  # the input is untouched


def test_resample_refuses_bad_rates(tmp_path: Path) -> None:
    path = _surrogate(tmp_path)  # 5.8 s long
    tr = read_trace(path)
    for rate in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(TraceError) as e:
            resample(tr, rate)
        assert str(e.value) == f"{path}: resampling rate must be a finite number of Hz > 0, got {rate!r}"
    with pytest.raises(TraceError) as e:
        resample(tr, 1.0)
    assert str(e.value) == f"{path}: resampling to 1 Hz leaves 6 samples over 5.8 s (at least 10 needed)"
    assert resample(tr, 1.0, min_samples=6).time_s.size == 6


def test_principal_amplitude() -> None:
    t = np.linspace(0, 2 * np.pi, 201)
    d = np.array([3.0, 4.0, 0.0]) / 5.0
    pts = np.outer(5.0 * np.sin(t), d) + np.array([1.0, 2.0, 3.0])
    assert principal_amplitude(pts) == pytest.approx(10.0)
    assert principal_amplitude(np.ones((5, 3))) == 0.0


def test_summary_points_csv(tmp_path: Path) -> None:
    path = _points_csv(tmp_path)
    s = trace_summary(read_trace(path))
    assert s["format"] == "points-csv"
    assert s["points"] == 2
    assert s["point_names"] == ["chest", "belly-2"]
    # chest moves (1, 0, -2) mm per sample over 10 steps; belly-2 0.25 mm per sample along y
    assert s["amplitude_mm"] == [pytest.approx(10 * np.sqrt(5.0), abs=1e-6), 2.5]
    assert s["amplitude_units"] == "mm"
    assert (s["samples"], s["duration_s"], s["rate_hz"], s["gaps"]) == (11, 5.0, 2.0, [])
    assert s["surrogate_amplitude"] is None
    assert s["rotation_amplitude_deg"] is None
    json.dumps(s)


def test_summary_surrogate_and_6dof(tmp_path: Path) -> None:
    s = trace_summary(read_trace(_surrogate(tmp_path)))
    assert s["points"] == 1
    assert s["amplitude_units"] == "arbitrary (surrogate units)"
    s6 = trace_summary(read_trace(_sixdof(tmp_path)))
    assert s6["points"] == 1
    assert s6["point_names"] == ["target"]
    assert s6["amplitude_mm"] == [pytest.approx(np.hypot(0.1, 0.5) * 29, abs=1e-6)]
    assert s6["rotation_amplitude_deg"] == [pytest.approx(0.29), pytest.approx(0.58), 0.0]


def test_trace_is_frozen(tmp_path: Path) -> None:
    tr: Trace = read_trace(_surrogate(tmp_path))
    with pytest.raises(AttributeError):
        tr.path = "x"  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        tr.time_s[0] = 1.0
