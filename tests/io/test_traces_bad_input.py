"""hil.io.traces: every kind of bad input gives one TraceError naming the file, the line and the problem."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.io.traces import TraceError, read_trace

HEADER = "time_s,p_x_mm,p_y_mm,p_z_mm"


def _rows(n: int, step: float = 0.5) -> list[str]:
    return [f"{step * i},{i},0,0" for i in range(n)]


def _expect(path: Path | str, message: str, *, line: int | None, **kw: object) -> None:
    with pytest.raises(TraceError) as e:
        read_trace(path, **kw)  # type: ignore[arg-type]
    assert str(e.value) == message
    assert e.value.line == line
    assert e.value.path == str(path) or message.startswith(e.value.path)


def _csv(tmp_path: Path, lines: list[str], name: str = "r.csv") -> Path:
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def test_missing_file_and_directory(tmp_path: Path) -> None:
    p = tmp_path / "nope.csv"
    _expect(p, f"{p}: no such file or directory", line=None)
    _expect(p, f"{p}: no such file or directory", line=None, format="paired")


def test_empty_file(tmp_path: Path) -> None:
    p = tmp_path / "e.txt"
    p.write_text("")
    _expect(p, f"{p}: empty file: no data rows", line=None)
    p.write_text("\n# only a comment\n   \n")
    _expect(p, f"{p}: empty file: no data rows", line=None)


def test_header_only(tmp_path: Path) -> None:
    p = _csv(tmp_path, [HEADER])
    _expect(p, f"{p}: no data rows after the header", line=None)


def test_wrong_column_count(tmp_path: Path) -> None:
    p = _csv(tmp_path, [HEADER, *_rows(5), "2.5,1,2", *_rows(20)[6:]])
    _expect(p, f"{p}:7: expected 4 columns, found 3", line=7)


def test_not_a_number(tmp_path: Path) -> None:
    p = _csv(tmp_path, [HEADER, *_rows(3), "1.5,1,two,3", *_rows(20)[4:]])
    _expect(p, f"{p}:5: column 3: not a number: 'two'", line=5)
    s = tmp_path / "s.txt"
    s.write_text("0 1\n0.2 1\n0.4 x\n")
    _expect(s, f"{s}:3: column 2: not a number: 'x'", line=3)


@pytest.mark.parametrize("bad", ["nan", "NaN", "inf", "-inf", "1e999"])
def test_nan_and_inf(tmp_path: Path, bad: str) -> None:
    p = _csv(tmp_path, [HEADER, *_rows(3), f"1.5,1,{bad},3", *_rows(20)[4:]])
    _expect(p, f"{p}:5: column 3: not a finite number: {bad!r}", line=5)


def test_nan_time_in_6dof(tmp_path: Path) -> None:
    p = tmp_path / "t.txt"
    p.write_text("0 0 0 0 0 0 0\nnan 0 0 0 0 0 0\n")
    _expect(p, f"{p}:2: column 1: not a finite number: 'nan'", line=2)


def test_time_going_back(tmp_path: Path) -> None:
    rows = _rows(20)
    rows[8] = "3.0,1,0,0"  # after 3.5
    p = _csv(tmp_path, [HEADER, *rows])
    _expect(p, f"{p}:10: time 3 s goes back from the previous sample's 3.5 s", line=10)


def test_repeated_time(tmp_path: Path) -> None:
    p = tmp_path / "s.txt"
    p.write_text("\n".join(["0 1", "0.2 1", "0.2 2", *(f"{0.2 * i:.1f} 1" for i in range(3, 40))]))
    _expect(p, f"{p}:3: time 0.2 s repeats the previous sample's 0.2 s", line=3)


def test_too_short(tmp_path: Path) -> None:
    p = _csv(tmp_path, [HEADER, *_rows(5)])
    _expect(p, f"{p}: too short: 5 samples (at least 10 needed)", line=None)
    p = _csv(tmp_path, [HEADER, *_rows(12, step=0.1)])
    _expect(p, f"{p}: too short: 1.1 s (at least 5 s needed)", line=None)
    assert read_trace(p, min_duration_s=1.0).time_s.size == 12
    _expect(p, f"{p}: too short: 12 samples (at least 20 needed)", line=None, min_duration_s=1.0,
            min_samples=20)


def test_unknown_format(tmp_path: Path) -> None:
    p = tmp_path / "four.txt"
    p.write_text("0 1 2 3\n0.2 1 2 3\n")
    _expect(p, f"{p}:1: unknown format (4 numeric columns; expected a time_s header, 2 columns "
            "(surrogate) or 7 (6dof))", line=1)
    q = tmp_path / "words.csv"
    q.write_text("\n\ntime,a,b\n0,1,2\n")
    _expect(q, f"{q}:3: unknown format (first line 'time,a,b' is neither a time_s header nor numbers)",
            line=3)
    _expect(q, f"{q}: unknown format 'xyz' (one of points-csv, surrogate, 6dof, paired)", line=None,
            format="xyz")


def test_units_cannot_be_told_points_csv(tmp_path: Path) -> None:
    p = _csv(tmp_path, ["time_s,p_x,p_y,p_z", *_rows(20)])
    _expect(p, f"{p}:1: column 'p_x' has no unit: units cannot be told (expected p_x_mm)", line=1)
    p = _csv(tmp_path, ["time_s,p_x_cm,p_y_cm,p_z_cm", *_rows(20)])
    _expect(p, f"{p}:1: column 'p_x_cm': unit 'cm' is not supported (positions are _mm)", line=1)
    p = _csv(tmp_path, ["time_ms,p_x_mm,p_y_mm,p_z_mm", *_rows(20)])
    _expect(p, f"{p}:1: first column is 'time_ms': the time unit cannot be told (expected 'time_s', "
            "seconds)", line=1, format="points-csv")
    p = _csv(tmp_path, ["time_s,p_x_mm,p_y_mm,amplitude", *_rows(20)])
    _expect(p, f"{p}:1: column 'amplitude' is not NAME_x_mm, NAME_y_mm or NAME_z_mm", line=1)


def test_points_csv_header_layout(tmp_path: Path) -> None:
    p = _csv(tmp_path, ["time_s,p_x_mm,p_y_mm", *_rows(20)])
    _expect(p, f"{p}:1: point 'p' lacks column(s) p_z_mm", line=1)
    p = _csv(tmp_path, ["time_s,p_x_mm,p_y_mm,p_x_mm", *_rows(20)])
    _expect(p, f"{p}:1: column 'p_x_mm' appears twice", line=1)
    p = _csv(tmp_path, ["time_s", "0", "1"])
    _expect(p, f"{p}:1: no point columns after time_s (expected NAME_x_mm,NAME_y_mm,NAME_z_mm)", line=1)


def test_headerless_time_not_in_seconds(tmp_path: Path) -> None:
    p = tmp_path / "ms.txt"
    p.write_text("\n".join(f"{200 * i} {i}" for i in range(40)))
    _expect(p, f"{p}: median time step 200 is not 0.0001-1 s: the time column's unit cannot be told "
            "(expected seconds)", line=None)


def test_6dof_translations_not_in_mm(tmp_path: Path) -> None:
    p = tmp_path / "big.txt"
    rows = [f"{0.2 * i:.1f} 0 {i * 10} 0 0 0 0" for i in range(40)]
    p.write_text("\n".join(rows))
    _expect(p, f"{p}:12: translation 110 exceeds 100 mm: units cannot be told (expected mm)", line=12)
    rows = [f"{0.2 * i:.1f} 0 0 0 {i * 10} 0 0" for i in range(40)]
    p.write_text("\n".join(rows))
    _expect(p, f"{p}:11: rotation 100 exceeds 90 deg: units cannot be told (expected deg)", line=11)


def _sidecar_case(tmp_path: Path, places: object) -> tuple[Path, Path]:
    p = _csv(tmp_path, ["time_s,a_x_mm,a_y_mm,a_z_mm,b_x_mm,b_y_mm,b_z_mm",
                        *(f"{0.5 * i},{i},0,0,0,{i},0" for i in range(20))])
    side = tmp_path / "r.csv.points.json"
    side.write_text(places if isinstance(places, str) else json.dumps(places))
    return p, side


def test_sidecar_errors(tmp_path: Path) -> None:
    p, side = _sidecar_case(tmp_path, {"a": [0, 0], "b": [1, 1], "c": [2, 2]})
    _expect(p, f"{side}: names point 'c', which {p} does not record", line=None)
    p, side = _sidecar_case(tmp_path, {"a": [0, 0]})
    _expect(p, f"{side}: lacks the place of point(s) 'b' of {p}", line=None)
    p, side = _sidecar_case(tmp_path, {"a": [0, 0], "b": [1, "x"]})
    _expect(p, f"{side}: point 'b': expected [x_mm, y_mm] (two finite numbers), got [1, 'x']", line=None)
    p, side = _sidecar_case(tmp_path, [[0, 0]])
    _expect(p, f'{side}: expected an object {{"NAME": [x_mm, y_mm], ...}}', line=None)
    p, side = _sidecar_case(tmp_path, '{\n"a": [0, 0],\n}')
    _expect(p, f"{side}:3: not valid JSON: Expecting property name enclosed in double quotes", line=3)


def _pair(tmp_path: Path, tumour: list[str] | None, resp: list[str] | None) -> Path:
    d = tmp_path / "pair"
    d.mkdir(exist_ok=True)
    if tumour is not None:
        (d / "x SI.txt").write_text("\n".join(tumour))
    if resp is not None:
        (d / "x_resp.txt").write_text("\n".join(resp))
    return d


def test_paired_errors(tmp_path: Path) -> None:
    tum = [f"{0.2 * i:.1f} 0 0 {i} 0 0 0" for i in range(40)]
    rsp = [f"{0.2 * i:.1f} {i}" for i in range(40)]
    d = _pair(tmp_path, tum, None)
    _expect(d, f"{d}: a paired directory holds one tumour file and one *resp* file; found 1 tumour "
            "file(s) and 0 *resp* file(s)", line=None)
    d = _pair(tmp_path, None, rsp)
    shifted = [f"{0.2 * i + 0.1:.1f} {i}" for i in range(40)]
    (d / "x_resp.txt").write_text("\n".join(shifted))
    _expect(d, f"{d}: x SI.txt and x_resp.txt do not share time stamps over their common span 0.1-7.8 s "
            "(first difference at x SI.txt line 2)", line=None)
    (d / "x_resp.txt").write_text("\n".join([*rsp[:5], "1.0 1 2", *rsp[6:]]))
    with pytest.raises(TraceError) as e:
        read_trace(d)
    assert str(e.value) == f"{d / 'x_resp.txt'}:6: expected 2 columns, found 3"
    f = tmp_path / "file.txt"
    f.write_text("0 1\n")
    _expect(f, f"{f}: the paired format reads a directory (one tumour file, one *resp* file)", line=None,
            format="paired")
    _expect(d, f"{d}: is a directory (only the paired format reads a directory)", line=None,
            format="6dof")
