"""`hil register`: JSON output on the seed-000 files, one stderr line + exit 2 on bad input."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.cli import main
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform
from hil.geometry.tre import expected_tre_mm
from hil.io import read_points

EX = Path(__file__).resolve().parents[2] / "configs" / "examples" / "seed000"
CT, BEFORE, AFTER = str(EX / "ct_markers.csv"), str(EX / "optical_before.csv"), str(EX / "optical_after.csv")


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict[str, object] | None, str]:
    code = main(["register", *argv])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if out.strip() else None), err


def test_seed000_ct_from_optical(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(capsys, CT, BEFORE)
    assert code == 0
    assert err == ""
    assert out is not None
    T = np.asarray(out["T"])
    assert T.shape == (4, 4)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    assert out["method"] == "horn"
    assert out["n_points"] == 4
    assert out["rigid"] is True
    assert out["fre_rms_mm"] == pytest.approx(6.238841, abs=1e-6)
    np.testing.assert_allclose(out["residuals_mm"], [2.978942, 4.102241, 7.289756, 8.766387], atol=1e-6)
    assert out["rotation_deg"] == pytest.approx(120.563518, abs=1e-6)
    np.testing.assert_allclose(out["translation_mm"], T[:3, 3])
    assert out["fle_source"] == "estimated_from_fre"
    assert out["fle_mm"] == pytest.approx(6.238841 * math.sqrt(2), abs=1e-5)
    # T maps MOVING (optical) points into FIXED's (CT) frame
    ct = read_points(CT).points_mm
    before = read_points(BEFORE).points_mm
    mapped = before @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(np.linalg.norm(mapped - ct, axis=1), out["residuals_mm"], atol=1e-5)


def test_target_and_tre_with_given_fle(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(capsys, BEFORE, CT, "--target=-60,-120,-1200", "--fle", "1.0", "--method", "svd")
    assert code == 0
    assert out is not None
    ct = read_points(CT).points_mm
    before = read_points(BEFORE).points_mm
    T = register_horn(before, ct).T_fixed_from_moving
    np.testing.assert_allclose(out["target_mapped"], T.apply([-60.0, -120.0, -1200.0]), atol=1e-5)
    assert out["target_moving"] == [-60.0, -120.0, -1200.0]
    assert out["tre_expected_mm"] == pytest.approx(expected_tre_mm(ct, [-60, -120, -1200], 1.0), abs=1e-6)
    assert out["fle_source"] == "given"
    assert out["fle_mm"] == 1.0
    assert out["fre_expected_mm"] == pytest.approx(math.sqrt(0.5), abs=1e-6)


def test_motion_between_before_and_after(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(capsys, AFTER, BEFORE)
    assert code == 0
    assert out is not None
    assert out["fre_rms_mm"] == pytest.approx(2.694689, abs=1e-6)
    assert out["rotation_deg"] == pytest.approx(16.006829, abs=1e-5)


def test_affine4_method(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(capsys, CT, BEFORE, "--method", "affine4", "--target", "0,0,900")
    assert code == 0
    assert out is not None
    assert out["rigid"] is False
    assert out["fre_rms_mm"] == 0.0
    assert out["tre_expected_mm"] is None
    T = np.asarray(out["T"])
    np.testing.assert_allclose(out["target_mapped"], T[:3, :3] @ [0, 0, 900] + T[:3, 3], atol=1e-4)


def test_exact_synthetic_files_in_every_format(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(3)
    moving = rng.uniform(-100, 100, size=(6, 3))
    T = RigidTransform.from_rotvec([0.5, -0.2, 1.0], [10.0, 20.0, 30.0])
    fixed = T.apply(moving)
    (tmp_path / "f.json").write_text(json.dumps({"points": fixed.tolist()}))
    cps = [{"position": p, "label": str(i)} for i, p in enumerate(moving.tolist())]
    doc = {"markups": [{"coordinateSystem": "LPS", "controlPoints": cps}]}
    (tmp_path / "m.mrk.json").write_text(json.dumps(doc))
    code, out, _ = _run(capsys, str(tmp_path / "f.json"), str(tmp_path / "m.mrk.json"))
    assert code == 0
    assert out is not None
    np.testing.assert_allclose(out["T"], np.round(T.as_matrix(), 6), atol=2e-6)
    assert out["fre_rms_mm"] == 0.0


def _bad(tmp_path: Path, name: str, text: str) -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize(
    ("make", "which", "reason"),
    [
        (lambda d: str(d / "missing.csv"), "fixed", "file not found"),
        (lambda d: _bad(d, "two.csv", "x,y,z\n1,2,3\n4,5,6\n"), "fixed",
         "has 2 point(s); registration needs at least 3"),
        (lambda d: _bad(d, "three.csv", "x,y,z\n1,2,3\n4,5,6\n0,9,1\n"), "moving",
         "has 3 points but"),
        (lambda d: _bad(d, "nan.csv", "x,y,z\n1,2,3\n4,5,nan\n0,9,1\n7,7,7\n"), "fixed", "NaN or infinite"),
        (lambda d: _bad(d, "line.csv", "x,y,z\n0,0,0\n1,1,1\n2,2,2\n5,5,5\n"), "fixed", "collinear"),
        (lambda d: _bad(d, "same.csv", "x,y,z\n1,1,1\n1,1,1\n1,1,1\n1,1,1\n"), "fixed", "coincide"),
        (lambda d: _bad(d, "junk.json", "{oops"), "fixed", "bad JSON"),
    ],
)
def test_bad_input_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make: object, which: str, reason: str
) -> None:
    bad = make(tmp_path)  # type: ignore[operator]
    argv = [bad, BEFORE] if which == "fixed" else [CT, bad]
    code, out, err = _run(capsys, *argv)
    assert code == 2
    assert out is None
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("hil register: error: ")
    assert bad in lines[0]
    assert reason in lines[0]


def test_affine4_rejects_wrong_count_and_coplanar(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    five = _bad(tmp_path, "five.csv", "x,y,z\n0,0,0\n10,0,0\n0,10,0\n0,0,10\n5,5,5\n")
    code, _, err = _run(capsys, five, five, "--method", "affine4")
    assert code == 2
    assert "needs exactly 4" in err
    flat = _bad(tmp_path, "flat.csv", "x,y,z\n0,0,0\n10,0,0\n0,10,0\n10,10,0\n")
    code, _, err = _run(capsys, flat, flat, "--method", "affine4")
    assert code == 2
    assert "coplanar" in err
    assert flat in err


@pytest.mark.parametrize(
    "argv", [["--target", "1,2"], ["--target", "a,b,c"], ["--fle", "-1"], ["--method", "icp"]]
)
def test_bad_options_are_usage_errors(capsys: pytest.CaptureFixture[str], argv: list[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["register", CT, BEFORE, *argv])
    assert info.value.code == 2
    assert "error" in capsys.readouterr().err


def test_console_script_subprocess() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "hil", "register", CT, BEFORE],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["fre_rms_mm"] == pytest.approx(6.238841, abs=1e-6)
    bad = subprocess.run(
        [sys.executable, "-m", "hil", "register", CT, "/nonexistent/points.csv"],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert bad.returncode == 2
    assert bad.stdout == ""
    assert bad.stderr.strip() == "hil register: error: /nonexistent/points.csv: file not found"
