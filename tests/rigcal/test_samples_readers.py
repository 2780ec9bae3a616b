"""Readers of recorded hand-eye samples (hil.rigcal.sample_readers) and their refusals, each with
its exact one-line message."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.rigcal.sample_readers import detect_format, read_samples
from hil.rigcal.samples import PosePairs, RecordedStreams, SamplesError, check_motion, transform
from tests.rigcal.samples_synth import easy_handeye_text, synth_pairs, write_csv_pairs, write_opencv_yaml


@pytest.fixture
def pairs() -> tuple[np.ndarray, np.ndarray]:
    _, _, B, C = synth_pairs(np.random.default_rng(7), 8, eye_in_hand=False)
    return B, C


def _same(got: PosePairs, B: np.ndarray, C: np.ndarray) -> None:
    assert len(got) == len(B)
    np.testing.assert_allclose(got.T_base_from_flange, B, atol=1e-9)
    np.testing.assert_allclose(got.T_camera_from_target, C, atol=1e-9)


def test_csv_position_quaternion_metres(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = tmp_path / "s.csv"
    write_csv_pairs(f, *pairs, scale=1e-3)
    got = read_samples(f, detect_format(f), eye_in_hand=False)
    assert isinstance(got, PosePairs)
    _same(got, *pairs)
    assert got.where[0] == "line 3"
    assert got.t_s is not None
    assert got.t_s[1] == pytest.approx(0.1)


def test_csv_matrix_millimetres(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = tmp_path / "s.csv"
    write_csv_pairs(f, *pairs, scale=1.0, layout="matrix")
    got = read_samples(f, "csv", eye_in_hand=False)
    assert isinstance(got, PosePairs)
    _same(got, *pairs)


def test_csv_with_one_stream_per_row_is_two_streams(tmp_path: Path) -> None:
    cols = "t," + ",".join(f"{s}_{c}" for s in ("robot", "camera")
                           for c in ("x", "y", "z", "qx", "qy", "qz", "qw"))
    rows = [cols]
    for k in range(6):
        rows.append(f"{0.02 * k:.2f},0.4,0.0,{0.3 + 0.001 * k},0,0,0,1" + ",,,,,,,")
        if k % 2 == 0:
            rows.append(f"{0.02 * k + 0.005:.3f},,,,,,,,0.1,0.2,{0.8 + 0.001 * k},0,0,0,1")
    f = tmp_path / "streams.csv"
    f.write_text("\n".join(rows) + "\n")
    got = read_samples(f, "csv", eye_in_hand=False)
    assert isinstance(got, RecordedStreams)
    assert len(got.robot.t_s) == 6
    assert len(got.camera.t_s) == 3
    assert got.camera.T[2, 2, 3] == pytest.approx(804.0)
    assert got.robot.where[1] == "line 4"   # line 3 is the first camera sample


def test_opencv_yaml(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = tmp_path / "pairs.yml"
    write_opencv_yaml(f, *pairs)
    assert detect_format(f) == "opencv-yaml"
    got = read_samples(f, "opencv-yaml", eye_in_hand=False)
    assert isinstance(got, PosePairs)
    _same(got, *pairs)
    assert got.where[:2] == ("pair 0", "pair 1")


@pytest.mark.parametrize("eye_in_hand", [False, True])
def test_easy_handeye(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray], eye_in_hand: bool) -> None:
    f = tmp_path / "calib.samples"
    f.write_text(easy_handeye_text(*pairs, eye_in_hand=eye_in_hand))
    assert detect_format(f) == "easy-handeye"
    got = read_samples(f, "easy-handeye", eye_in_hand=eye_in_hand)
    assert isinstance(got, PosePairs)
    _same(got, *pairs)   # eye-on-base robot samples (T_effector_from_base) come back inverted


def _csv_one_bad(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray], M: np.ndarray) -> Path:
    B, C = pairs
    B = B.copy()
    B[0] = M
    f = tmp_path / "bad.csv"
    write_csv_pairs(f, B, C, scale=1.0, layout="matrix")
    return f


def _message(f: Path, fmt: str, eye_in_hand: bool = False) -> str:
    with pytest.raises(SamplesError) as exc:
        read_samples(f, fmt, eye_in_hand)
    return str(exc.value)


def test_not_orthonormal(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = _csv_one_bad(tmp_path, pairs, transform(1.1 * np.eye(3), np.array([400.0, 0.0, 300.0])))
    assert _message(f, "csv") == (f"{f}: line 3 (robot): the rotation is not orthonormal "
                                  "(|R^T R - I| = 0.21 > 0.001)")


def test_reflection(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = _csv_one_bad(tmp_path, pairs, transform(np.diag([1.0, 1.0, -1.0]), np.array([400.0, 0.0, 300.0])))
    assert _message(f, "csv") == (f"{f}: line 3 (robot): the rotation has determinant -1.000, not +1 "
                                  "(a reflection)")


def test_nan(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    M = np.eye(4)
    M[1, 3] = np.nan
    f = _csv_one_bad(tmp_path, pairs, M)
    assert _message(f, "csv") == f"{f}: line 3 (robot): not a finite number (NaN or inf)"


def test_not_a_number(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = tmp_path / "s.csv"
    write_csv_pairs(f, *pairs)
    lines = f.read_text().splitlines()
    cells = lines[3].split(",")
    cells[2] = "abc"
    lines[3] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")
    assert _message(f, "csv") == f"{f}: line 4 (robot): 'abc' is not a number"


def test_quaternion_not_unit(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = tmp_path / "s.csv"
    write_csv_pairs(f, *pairs)
    lines = f.read_text().splitlines()
    cells = lines[2].split(",")
    cells[11:15] = ["0", "0", "0", "1.1"]   # camera qx qy qz qw
    lines[2] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")
    assert _message(f, "csv") == (f"{f}: line 3 (camera): the quaternion has norm 1.1000, not 1 "
                                  "(tolerance 0.001; order is qx, qy, qz, qw)")


def test_units_cannot_be_told(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    B, C = pairs
    B = B.copy()
    B[:, :3, 3] = [6.0, 8.0, 0.0]            # 10 units from the base: neither metres nor mm
    f = tmp_path / "s.csv"
    write_csv_pairs(f, B, C, scale=1.0)
    assert _message(f, "csv") == (f"{f}: robot poses: units cannot be told: the median translation is 10 "
                                  "(metres expected in 0.01..5, millimetres in 20..5000)")


def test_yaml_mismatched_counts(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = tmp_path / "pairs.yml"
    write_opencv_yaml(f, *pairs, count=9)
    assert _message(f, "opencv-yaml") == f"{f}: mismatched counts: frameCount 9, 8 T1_i and 8 T2_i"


def test_easy_handeye_setup_mismatch(tmp_path: Path, pairs: tuple[np.ndarray, np.ndarray]) -> None:
    f = tmp_path / "calib.samples"
    f.write_text(easy_handeye_text(*pairs, eye_in_hand=False))
    assert _message(f, "easy-handeye", eye_in_hand=True) == (
        f"{f}: the file says calibration_type 'eye_on_base'; give the matching --setup")


def test_easy_handeye_sample_without_tracking(tmp_path: Path) -> None:
    f = tmp_path / "calib.samples"
    f.write_text("samples:\n- robot:\n    translation: {x: 0.4, y: 0, z: 0.3}\n"
                 "    rotation: {x: 0, y: 0, z: 0, w: 1}\n")
    assert _message(f, "easy-handeye") == f"{f}: sample 0: needs both 'robot' and 'tracking'"


def test_unknown_format(tmp_path: Path) -> None:
    f = tmp_path / "poses.txt"
    f.write_text("1 2 3\n")
    with pytest.raises(SamplesError) as exc:
        detect_format(f)
    assert str(exc.value) == (f"{f}: unknown format (give --format, one of csv, opencv-yaml, "
                              "easy-handeye, eth, session-log)")


def test_eth_is_eye_in_hand_only(tmp_path: Path) -> None:
    f = tmp_path / "rec.zip"
    assert _message(f, "eth", eye_in_hand=False) == (
        f"{f}: the eth format is eye-in-hand (the camera rides on the hand); use --setup eye-in-hand")


def test_too_few_pairs(pairs: tuple[np.ndarray, np.ndarray]) -> None:
    B, C = pairs
    p = PosePairs(B[:4], C[:4], tuple(f"pair {i}" for i in range(4)))
    with pytest.raises(SamplesError) as exc:
        check_motion(p, "f.yml")
    assert str(exc.value) == "f.yml: too few pairs: 4 (need >= 6)"


def test_rotation_about_one_axis_is_degenerate() -> None:
    from scipy.spatial.transform import Rotation

    B = np.array([transform(Rotation.from_euler("z", 10.0 * k, degrees=True).as_matrix(),
                            np.array([400.0 + k, 0.0, 300.0])) for k in range(8)])
    p = PosePairs(B, B.copy(), tuple(f"pair {i}" for i in range(8)))
    with pytest.raises(SamplesError) as exc:
        check_motion(p, "f.yml")
    assert re.fullmatch(r"f\.yml: degenerate motion: the robot rotates \(almost\) only about the axis "
                        r"\[-?0\.0, -?0\.0, -?1\.0\] \(base frame; spread ratio 0\.000 < 0\.1\); "
                        r"add poses tilted about another axis", str(exc.value)), str(exc.value)


def test_too_little_rotation() -> None:
    B = np.array([transform(np.eye(3), np.array([400.0 + 10 * k, 0.0, 300.0])) for k in range(8)])
    p = PosePairs(B, B.copy(), tuple(f"pair {i}" for i in range(8)))
    with pytest.raises(SamplesError) as exc:
        check_motion(p, "f.yml")
    assert str(exc.value) == ("f.yml: degenerate motion: the robot rotates at most 0.00 deg between "
                              "two poses (need >= 5 deg)")


@settings(max_examples=25)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(5, 12), metres=st.booleans(),
       layout=st.sampled_from(["quat", "matrix"]))
def test_csv_round_trip_property(tmp_path_factory: pytest.TempPathFactory, seed: int, n: int, metres: bool,
                                 layout: str) -> None:
    """Any poses written in either layout and unit come back in mm (units judged per stream)."""
    _, _, B, C = synth_pairs(np.random.default_rng(seed), n, eye_in_hand=bool(seed % 2))
    f = tmp_path_factory.mktemp("csv") / "s.csv"
    write_csv_pairs(f, B, C, scale=1e-3 if metres else 1.0, layout=layout)
    got = read_samples(f, "csv", eye_in_hand=False)
    assert isinstance(got, PosePairs)
    np.testing.assert_allclose(got.T_base_from_flange, B, atol=1e-9)
    np.testing.assert_allclose(got.T_camera_from_target, C, atol=1e-9)


@given(q=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_quaternion_scalar_last_property(q: list[float]) -> None:
    """Our (qx, qy, qz, qw) parser agrees with scipy's scalar-last quaternions."""
    from scipy.spatial.transform import Rotation

    from hil.rigcal.samples import quaternion_xyzw_to_matrix

    v = np.array(q) / np.linalg.norm(q)
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(v, "f", "here"), Rotation.from_quat(v).as_matrix(),
                               atol=1e-12)


def test_header_only(tmp_path: Path) -> None:
    f = tmp_path / "s.csv"
    write_csv_pairs(f, np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
    assert _message(f, "csv") == f"{f}: no pose pairs in the file"


def test_streams_that_do_not_overlap(tmp_path: Path) -> None:
    from hil.rigcal.streams import align_streams

    f = tmp_path / "s.csv"
    cols = "t," + ",".join(f"{s}_{c}" for s in ("robot", "camera")
                           for c in ("x", "y", "z", "qx", "qy", "qz", "qw"))
    rows = [cols] + [f"{k},0.4,0,0.3,0,0,0,1,,,,,,," for k in range(3)] \
        + [f"{k},,,,,,,,0.1,0.2,0.8,0,0,0,1" for k in range(5, 8)]
    f.write_text("\n".join(rows) + "\n")
    got = read_samples(f, "csv", eye_in_hand=False)
    assert isinstance(got, RecordedStreams)
    with pytest.raises(SamplesError) as exc:
        align_streams(got, str(f))
    assert str(exc.value) == (f"{f}: the streams overlap for 0.00 s only (robot 0.000..2.000 s, camera "
                              "5.000..7.000 s; need >= 1 s)")
