"""hil.io.points.read_points: CSV, JSON, Slicer .mrk.json/.fcsv, conventions and every error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hil.errors import InputFileError
from hil.io import read_points

EXAMPLES = Path(__file__).resolve().parents[2] / "configs" / "examples" / "seed000"
CT = [
    [-17.91, -67.45, -1225.5], [-13.4, -107.17, -1105.5],
    [-88.75, -121.47, -1114.3], [-112.63, -222.2, -1360.7],
]


def _write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    p = tmp_path / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize("name", ["ct_markers.csv", "ct_markers.fcsv", "ct_markers.mrk.json"])
def test_seed000_example_files_agree(name: str) -> None:
    ps = read_points(EXAMPLES / name)
    np.testing.assert_array_equal(ps.points_mm, CT)
    assert ps.labels == ("mark1", "mark2", "mark3", "mark4")
    assert len(ps) == 4
    assert not ps.points_mm.flags.writeable


@pytest.mark.parametrize(
    ("text", "labels"),
    [
        ("x,y,z\n1,2,3\n4,5,6\n7,8,9\n", ("1", "2", "3")),
        ("# comment\nlabel,x,y,z\na,1,2,3\nb,4,5,6\n\nc,7,8,9\n", ("a", "b", "c")),
        ("name;X_mm;Y_mm;Z_mm\na;1;2;3\nb;4;5;6\nc;7;8;9\n", ("a", "b", "c")),
        ("z,x,y\n3,1,2\n6,4,5\n9,7,8\n", ("1", "2", "3")),
        ("1,2,3\n4,5,6\n7,8,9\n", ("1", "2", "3")),
        ("1 2 3\n4\t5\t6\n7 8   9\n", ("1", "2", "3")),
        ("a,1,2,3\nb,4,5,6\nc,7,8,9\n", ("a", "b", "c")),
        ("1,2,3,a\n4,5,6,b\n7,8,9,c\n", ("a", "b", "c")),
        ("\ufeffx,y,z\r\n1,2,3\r\n4,5,6\r\n7,8,9\r\n", ("1", "2", "3")),
    ],
)
def test_csv_layouts(tmp_path: Path, text: str, labels: tuple[str, ...]) -> None:
    ps = read_points(_write(tmp_path, "p.csv", text))
    np.testing.assert_array_equal(ps.points_mm, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    assert ps.labels == labels
    assert ps.coordinate_system is None


@pytest.mark.parametrize(
    "doc",
    [
        [[1, 2, 3], [4, 5, 6]],
        {"points": [[1, 2, 3], [4, 5, 6]]},
        [{"x": 1, "y": 2, "z": 3, "label": "a"}, {"x": 4, "y": 5, "z": 6, "name": "b"}],
        {"points": [{"position": [1, 2, 3], "id": "a"}, {"position": [4, 5, 6], "label": "b"}]},
    ],
)
def test_json_layouts(tmp_path: Path, doc: object) -> None:
    ps = read_points(_write(tmp_path, "p.json", json.dumps(doc)))
    np.testing.assert_array_equal(ps.points_mm, [[1, 2, 3], [4, 5, 6]])
    assert len(ps.labels) == 2


def _mrk(cs: str, positions: list[list[float]], **extra: object) -> str:
    cps = [
        {"label": f"F-{i + 1}", "position": p, "positionStatus": "defined"} for i, p in enumerate(positions)
    ]
    markup = {"type": "Fiducial", "coordinateSystem": cs, "controlPoints": cps, **extra}
    return json.dumps({"markups": [markup]})


def test_mrk_json_ras_is_converted_to_lps_by_default(tmp_path: Path) -> None:
    ras = _write(tmp_path, "a.mrk.json", _mrk("RAS", [[1.0, 2.0, 3.0], [-4.0, 5.0, -6.0]]))
    ps = read_points(ras)
    np.testing.assert_array_equal(ps.points_mm, [[-1, -2, 3], [4, -5, -6]])
    assert (ps.source_coordinate_system, ps.coordinate_system) == ("RAS", "LPS")
    as_ras = read_points(ras, coordinate_system="RAS").points_mm
    np.testing.assert_array_equal(as_ras, [[1, 2, 3], [-4, 5, -6]])
    plain_name = _write(tmp_path, "c.json", _mrk("RAS", [[1.0, 2.0, 3.0]]))
    np.testing.assert_array_equal(read_points(plain_name).points_mm, [[-1, -2, 3]])
    lps = _write(tmp_path, "b.mrk.json", _mrk("LPS", [[1.0, 2.0, 3.0]]))
    np.testing.assert_array_equal(read_points(lps).points_mm, [[1, 2, 3]])
    np.testing.assert_array_equal(read_points(lps, coordinate_system="RAS").points_mm, [[-1, -2, 3]])


@pytest.mark.parametrize(("header", "sign"), [("LPS", 1), ("1", 1), ("RAS", -1), ("0", -1), (None, -1)])
def test_fcsv_coordinate_system(tmp_path: Path, header: str | None, sign: int) -> None:
    lines = ["# Markups fiducial file version = 4.11"]
    if header is not None:
        lines.append(f"# CoordinateSystem = {header}")
    lines += [
        "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID",
        "vtkMRMLMarkupsFiducialNode_0,1.5,2.5,3.5,0,0,0,1,1,1,0,F-1,,",
        "vtkMRMLMarkupsFiducialNode_1,-4,5,6,0,0,0,1,1,1,0,F-2,,",
    ]
    ps = read_points(_write(tmp_path, "p.fcsv", "\n".join(lines) + "\n"))
    np.testing.assert_array_equal(ps.points_mm, [[1.5 * sign, 2.5 * sign, 3.5], [-4 * sign, 5 * sign, 6]])
    assert ps.labels == ("F-1", "F-2")


@settings(max_examples=40)
@given(arrays(np.float64, st.tuples(st.integers(1, 20), st.just(3)),
              elements=st.floats(-1e4, 1e4, allow_nan=False, allow_subnormal=False)))
def test_round_trip_exact(tmp_path_factory: pytest.TempPathFactory, pts: np.ndarray) -> None:
    d = tmp_path_factory.mktemp("rt")
    csv = "x,y,z\n" + "".join(f"{a!r},{b!r},{c!r}\n" for a, b, c in pts.tolist())
    np.testing.assert_array_equal(read_points(_write(d, "p.csv", csv)).points_mm, pts)
    np.testing.assert_array_equal(read_points(_write(d, "p.json", json.dumps(pts.tolist()))).points_mm, pts)
    mrk = _write(d, "p.mrk.json", _mrk("LPS", pts.tolist()))
    np.testing.assert_array_equal(read_points(mrk).points_mm, pts)


@pytest.mark.parametrize(
    ("name", "content", "reason"),
    [
        ("p.csv", "", "no points"),
        ("p.csv", "# only a comment\n", "no points"),
        ("p.csv", "x,y,z\n", "no points"),
        ("p.csv", "x,y,z\n1,2,nan\n", "NaN or infinite"),
        ("p.csv", "1,2,inf\n", "NaN or infinite"),
        ("p.csv", "x,y,z\n1,2,abc\n", "'abc' is not a number"),
        ("p.csv", "x,y,z\n1,2\n", "fewer than the header"),
        ("p.csv", "1,2,3\n4,5\n", "expected x,y,z"),
        ("p.csv", "a,b,c\n1,2,3\n", "header must name columns x, y, z"),
        ("p.csv", b"\xff\xfe\x00binary", "not a UTF-8 text file"),
        ("p.json", "{not json", "bad JSON"),
        ("p.json", '{"pts": []}', "no 'points' key"),
        ("p.json", "[[1, 2]]", "expected [x, y, z]"),
        ("p.json", '[{"x": 1, "y": 2}]', "missing z"),
        ("p.json", "[[1, 2, NaN]]", "NaN or infinite"),
        ("p.json", '[[1, 2, "a"]]', "not a number"),
        ("p.json", "[[1, 2, true]]", "expected a number"),
        ("p.json", "[[1, 2, 1" + "0" * 400 + "]]", "out of range"),
        ("p.json", "[[1, 2, 1e999]]", "NaN or infinite"),
        ("p.json", "[]", "no points"),
        ("p.json", "[" * 100_000, "nested too deeply"),
        ("p.mrk.json", "[" * 100_000, "nested too deeply"),
        ("p.json", "1" * 5000, "Exceeds the limit (4300 digits)"),
        ("p.mrk.json", '{"markups": [' + "7" * 5000 + "]}", "Exceeds the limit (4300 digits)"),
        ("p.json", "5", "expected a JSON list"),
        ("p.mrk.json", '{"a": 1}', "not a Slicer markups file"),
        ("p.mrk.json", _mrk("IJK", [[1.0, 2.0, 3.0]]), "unsupported coordinate system"),
        ("p.mrk.json", _mrk("LPS", [[1.0, 2.0, 3.0]], coordinateUnits="um"), "coordinateUnits"),
        ("p.mrk.json", _mrk("LPS", [[1.0, 2.0]]), "expected [x, y, z]"),
        ("p.mrk.json", json.dumps({"markups": [{"controlPoints": [{"position": [1, 2, 3],
                                                                    "positionStatus": "undefined"}]}]}),
         "'undefined'"),
        ("p.fcsv", "# columns = id,a,b,c\n1,2,3,4\n", "no x, y, z columns"),
        ("p.fcsv", "# CoordinateSystem = 2\n1,2,3,4\n", "unsupported coordinate system"),
        ("p.fcsv", "1,2,3\n", "fields"),
    ],
)
def test_errors_name_file_and_problem(tmp_path: Path, name: str, content: str | bytes, reason: str) -> None:
    p = _write(tmp_path, name, content)
    with pytest.raises(InputFileError) as info:
        read_points(p)
    assert info.value.path == str(p)
    assert reason in info.value.reason


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="file not found"):
        read_points(tmp_path / "nope.csv")
    with pytest.raises(InputFileError, match="is a directory"):
        read_points(tmp_path)


_CSV_ALPHABET = st.sampled_from(list("0123456789.,-+eE;\t #\nxyzlabnNIf\"'"))


@settings(max_examples=300)
@given(
    st.sampled_from(["p.csv", "p.json", "p.fcsv", "p.mrk.json"]),
    st.one_of(st.text(_CSV_ALPHABET, max_size=80), st.text(max_size=60),
              st.builds(json.dumps, st.recursive(
                  st.none() | st.booleans() | st.floats() | st.text(max_size=5),
                  lambda c: st.lists(c, max_size=4) | st.dictionaries(
                      st.sampled_from(["points", "x", "y", "z", "position", "markups", "controlPoints",
                                       "coordinateSystem", "label"]), c, max_size=4),
                  max_leaves=12))),
)
def test_fuzz_only_input_file_errors(tmp_path_factory: pytest.TempPathFactory, name: str, text: str) -> None:
    """Whatever the bytes, the reader returns finite points or raises InputFileError — nothing else."""
    p = tmp_path_factory.mktemp("fz") / name
    p.write_text(text, encoding="utf-8", errors="surrogatepass")
    error: InputFileError | None = None
    try:
        ps = read_points(p)
    except InputFileError as exc:
        error = exc
    if error is not None:
        assert error.path == str(p)
        assert error.reason
    else:
        assert ps.points_mm.ndim == 2
        assert ps.points_mm.shape[1] == 3
        assert ps.points_mm.shape[0] >= 1
        assert np.all(np.isfinite(ps.points_mm))
        assert len(ps.labels) == len(ps)
