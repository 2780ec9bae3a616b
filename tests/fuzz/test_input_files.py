"""Files from outside: setup configs (TOML), plans, point lists and stereo calibrations.

Random and mutated files must give a correct parse or the loader's typed error naming the file;
a file that loads must hold only finite numbers (no NaN/inf slipping through as a value)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.config import load_setup
from hil.controller.plan_file import load_plan
from hil.errors import CalibrationError, ConfigError, HilError, InputFileError
from hil.io.points import read_points
from hil.vision.camera_model import load_calibration

from .strategies import json_values, mutated_bytes, mutated_json, outcome

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
PLAN_DOC = json.loads((CONFIGS / "plans" / "sim_plan.json").read_text())
CAL_DOC = json.loads((CONFIGS / "calibration" / "sim_stereo.json").read_text())


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("fuzz_files")
    shutil.copytree(CONFIGS / "calibration", d / "calibration")
    shutil.copytree(CONFIGS / "plans", d / "plans")
    return d


def _finite_numbers(node: Any, where: str = "") -> list[str]:
    """Paths of non-finite floats in a dumped model."""
    if isinstance(node, float):
        return [] if math.isfinite(node) else [where]
    if isinstance(node, dict):
        return [p for k, v in node.items() for p in _finite_numbers(v, f"{where}.{k}")]
    if isinstance(node, list | tuple):
        return [p for i, v in enumerate(node) for p in _finite_numbers(v, f"{where}[{i}]")]
    return []


# ----------------------------------------------------------------------------- setup configs
# nan / inf / -inf are left out: configs accept them today (pydantic's default allow_inf_nan), a
# known defect with its own reproducers in test_known_bugs.py (test_infinite_*).
TOML_TOKENS = [
    "-1",
    "0",
    "1e308",
    "1e-320",
    "true",
    '"x"',
    "[]",
    "{}",
    "[1, 2]",
    "'''",
    "= =",
    "9" * 30,
    "[[faults]]",
    "[camera]",
    '"../../../../etc/passwd"',
    '"\\u0000"',
]


@st.composite
def mutated_toml(draw: st.DrawFn) -> bytes:
    text = (CONFIGS / draw(st.sampled_from(["sim.toml", "sim_faults.toml"]))).read_text()
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["value", "value", "delete", "duplicate", "swap"]))
        if op == "value" and "=" in lines[i]:
            key = lines[i].split("=", 1)[0]
            lines[i] = f"{key}= {draw(st.sampled_from(TOML_TOKENS))}"
        elif op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
    raw = ("\n".join(lines) + "\n").encode()
    if draw(st.integers(0, 4)) == 0:
        raw = draw(mutated_bytes(raw))
    return raw


def _check_setup(path: Path) -> None:
    res = outcome(lambda: load_setup(path), (ConfigError,))
    if isinstance(res, ConfigError):
        assert str(path) in str(res)
        assert res.problems
        return
    bad = _finite_numbers(res.model_dump(mode="python"))
    assert not bad, f"config loaded with non-finite values at {bad}"


@settings(max_examples=250)
@given(mutated_toml())
def test_mutated_setup_config(workdir: Path, raw: bytes) -> None:
    p = workdir / "mutated.toml"
    p.write_bytes(raw)
    _check_setup(p)


@settings(max_examples=100)
@given(st.binary(max_size=300))
def test_random_bytes_as_setup_config(workdir: Path, raw: bytes) -> None:
    p = workdir / "random.toml"
    p.write_bytes(raw)
    _check_setup(p)


# ----------------------------------------------------------------------------- plans
def _check_plan(path: Path, doc: Any) -> None:
    res = outcome(lambda: load_plan(path), (InputFileError,))
    if isinstance(res, InputFileError):
        assert res.path == str(path)
        return
    # loaded: it is exactly what the file said
    assert np.array_equal(res.fiducials_mm, np.asarray(doc["fiducials_mm"], dtype=float))
    assert np.array_equal(res.entry_mm, np.asarray(doc["entry_mm"], dtype=float).reshape(3))
    assert np.array_equal(res.target_mm, np.asarray(doc["target_mm"], dtype=float).reshape(3))
    assert np.all(np.isfinite(res.fiducials_mm))


@settings(max_examples=250)
@given(mutated_json(PLAN_DOC))
def test_mutated_plan(workdir: Path, doc: Any) -> None:
    p = workdir / "plan.json"
    p.write_text(json.dumps(doc))  # NaN / Infinity tokens included
    _check_plan(p, doc)


@settings(max_examples=100)
@given(st.binary(max_size=200))
def test_random_bytes_as_plan(workdir: Path, raw: bytes) -> None:
    p = workdir / "plan_random.json"
    p.write_bytes(raw)
    outcome(lambda: load_plan(p), (InputFileError,))


# ----------------------------------------------------------------------------- calibrations
@settings(max_examples=200)
@given(mutated_json(CAL_DOC))
def test_mutated_calibration(workdir: Path, doc: Any) -> None:
    p = workdir / "cal.json"
    p.write_text(json.dumps(doc))
    res = outcome(lambda: load_calibration(p), (CalibrationError, InputFileError))
    if isinstance(res, HilError):
        assert str(p) in str(res)
        return
    for name in ("K_left", "K_right", "dist_left", "dist_right", "R_right_from_left", "t_right_from_left_mm"):
        arr = np.asarray(getattr(res, name))
        assert np.all(np.isfinite(arr)), name
    assert np.allclose(res.K_left, np.asarray(doc["left"]["K"], dtype=float))
    assert np.allclose(res.t_right_from_left_mm, np.asarray(doc["t_right_from_left_mm"], dtype=float))
    R = res.R_right_from_left
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-6)


@settings(max_examples=100)
@given(st.binary(max_size=200))
def test_random_bytes_as_calibration(workdir: Path, raw: bytes) -> None:
    p = workdir / "cal_random.json"
    p.write_bytes(raw)
    outcome(lambda: load_calibration(p), (CalibrationError, InputFileError))


# ----------------------------------------------------------------------------- point files
POINT_SUFFIXES = [".csv", ".txt", ".json", ".mrk.json", ".fcsv"]
number_cells = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["", "x", "1,5", "1e999", "-0", "nan", "inf", "0x10", " ", "\t", "#", '"', "1e-400"]),
)


@st.composite
def point_texts(draw: st.DrawFn) -> str:
    kind = draw(st.sampled_from(["rows", "json", "fcsv", "text"]))
    if kind == "rows":
        sep = draw(st.sampled_from([",", ";", "\t", " "]))
        rows = draw(st.lists(st.lists(number_cells, min_size=0, max_size=5), max_size=6))
        header = draw(st.sampled_from(["", "x,y,z\n", "label,x_mm,y_mm,z_mm\n", "# comment\n"]))
        return header + "\n".join(sep.join(r) for r in rows)
    if kind == "json":
        return json.dumps(draw(json_values))
    if kind == "fcsv":
        cs = draw(st.sampled_from(["LPS", "RAS", "0", "1", "XYZ", ""]))
        rows = draw(st.lists(st.lists(number_cells, min_size=0, max_size=6), max_size=4))
        return (
            f"# Markups fiducial file version = 4.11\n# CoordinateSystem = {cs}\n"
            "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
            + "\n".join(",".join(r) for r in rows)
        )
    return draw(st.text(max_size=200))


@settings(max_examples=300)
@given(st.sampled_from(POINT_SUFFIXES), point_texts())
def test_point_files(workdir: Path, suffix: str, text: str) -> None:
    p = workdir / f"points{suffix}"
    p.write_text(text, encoding="utf-8")
    res = outcome(lambda: read_points(p), (InputFileError,))
    if isinstance(res, InputFileError):
        assert res.path == str(p)
        return
    assert res.points_mm.ndim == 2
    assert res.points_mm.shape[1] == 3
    assert len(res) >= 1
    assert np.all(np.isfinite(res.points_mm))
    assert len(res.labels) == len(res)


@settings(max_examples=100)
@given(st.sampled_from(POINT_SUFFIXES), st.binary(max_size=200))
def test_point_files_random_bytes(workdir: Path, suffix: str, raw: bytes) -> None:
    p = workdir / f"points_raw{suffix}"
    p.write_bytes(raw)
    outcome(lambda: read_points(p), (InputFileError,))
