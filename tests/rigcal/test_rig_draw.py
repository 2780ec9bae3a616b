"""Rigs drawn within tolerances (hil/rigcal/draw.py): every draw inside its bands, the same seed
the same rig, the placements applied as one camera motion, the tolerances file's bad input one
line, and the documented table the model's."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.config import SetupConfig
from hil.config.reference import model_table
from hil.config.simulation import RigErrorsConfig
from hil.errors import InputFileError
from hil.rigcal.draw import BAND_KNOBS, RigDraw, RigTolerances, apply_draw, draw_rig, load_tolerances
from tests.rigcal.conftest import REPO

#: Each knob's hard bounds (RigErrorsConfig's) the generated bands stay within.
_BOUNDS = {"flange_marker_error_mm": (0.0, 5.0), "camera_calibration_error_px": (0.0, 5.0),
           "camera_reception_offset_ms": (0.0, 200.0), "camera_timestamp_jitter_ms": (0.0, 20.0),
           "robot_state_latency_ms": (0.0, 100.0), "robot_joint_offset_error_rad": (0.0, 0.01),
           "tracker_clock_offset_ms": (-200.0, 200.0), "camera_clock_rate_error_ppm": (-500.0, 500.0)}
TABLE_TITLE = "rig tolerances: tools/bench accuracy --tolerances FILE"


@st.composite
def tolerances(draw: st.DrawFn) -> RigTolerances:
    bands = {}
    for k in BAND_KNOBS:
        lo, hi = _BOUNDS[k]
        a = draw(st.floats(lo, hi, allow_nan=False))
        b = draw(st.floats(lo, hi, allow_nan=False))
        bands[k] = (min(a, b), max(a, b))
    place = st.floats(0.0, 200.0, allow_nan=False)
    deg = st.floats(0.0, 10.0, allow_nan=False)
    return RigTolerances(**bands, camera_placement_mm=draw(place), camera_placement_deg=draw(deg),
                         tracker_placement_mm=draw(place), tracker_placement_deg=draw(deg))


def _placement_within(T: object, mm: float, deg: float) -> bool:
    t = getattr(T, "translation_mm", None)
    r = getattr(T, "rotvec_rad", None)
    assert t is not None
    assert r is not None
    return all(abs(x) <= mm for x in t) and all(abs(x) <= math.radians(deg) for x in r)


@given(seed=st.integers(0, 2**40), tol=tolerances())
def test_every_draw_lies_within_its_tolerances(seed: int, tol: RigTolerances) -> None:
    d = draw_rig(seed, tol)
    assert d.seed == seed
    for k in BAND_KNOBS:
        lo, hi = getattr(tol, k)
        assert lo <= getattr(d.rig_errors, k) <= hi, k
    assert d.rig_errors.camera_timestamp == tol.camera_timestamp
    assert _placement_within(d.T_camera_from_nominal_camera, tol.camera_placement_mm,
                             tol.camera_placement_deg)
    assert _placement_within(d.T_tracker_from_nominal_tracker, tol.tracker_placement_mm,
                             tol.tracker_placement_deg)


@given(seed=st.integers(0, 2**40), tol=tolerances())
def test_the_same_seed_gives_the_same_rig(seed: int, tol: RigTolerances) -> None:
    a = draw_rig(seed, tol)
    b = draw_rig(seed, RigTolerances.model_validate(tol.model_dump(mode="json")))  # as a task carries it
    assert a == b
    assert RigDraw.model_validate_json(a.model_dump_json()) == a


def test_seeds_give_different_rigs_and_zero_bands_give_exact_values() -> None:
    tol = RigTolerances()
    draws = [draw_rig(k, tol) for k in range(20)]
    assert len({d.rig_errors.camera_reception_offset_ms for d in draws}) == 20
    fixed = RigTolerances(**{k: (0.25, 0.25) for k in BAND_KNOBS if _BOUNDS[k][0] <= 0.25 <= _BOUNDS[k][1]
                             and k != "robot_joint_offset_error_rad"},
                          robot_joint_offset_error_rad=(0.001, 0.001), camera_placement_mm=0.0,
                          camera_placement_deg=0.0, tracker_placement_mm=0.0, tracker_placement_deg=0.0)
    d = draw_rig(5, fixed)
    assert d.rig_errors.flange_marker_error_mm == 0.25
    assert d.rig_errors.robot_joint_offset_error_rad == 0.001
    assert d.T_camera_from_nominal_camera.translation_mm == (0.0, 0.0, 0.0)


def test_a_negative_seed_is_refused() -> None:
    with pytest.raises(ValueError, match="seed must be >= 0"):
        draw_rig(-1, RigTolerances())


def test_apply_draw_moves_the_camera_not_the_room(realistic: SetupConfig) -> None:
    sim = realistic.simulation
    d = draw_rig(11, RigTolerances(camera_placement_mm=50.0, camera_placement_deg=5.0))
    moved = apply_draw(sim, d)
    assert moved.seed == 11
    assert moved.rig_errors == d.rig_errors
    # the robot base and the patient keep their relative pose; the camera sees both moved by D
    before = (sim.patient.T_optical_from_image.as_transform().inverse()
              @ sim.T_optical_from_robot.as_transform())
    after = (moved.patient.T_optical_from_image.as_transform().inverse()
             @ moved.T_optical_from_robot.as_transform())
    np.testing.assert_allclose(after.as_matrix(), before.as_matrix(), atol=1e-9)
    D = d.T_camera_from_nominal_camera.as_transform()
    np.testing.assert_allclose(moved.T_optical_from_robot.as_transform().as_matrix(),
                               (D @ sim.T_optical_from_robot.as_transform()).as_matrix(), atol=1e-9)
    E = d.T_tracker_from_nominal_tracker.as_transform()
    np.testing.assert_allclose(
        moved.T_optical_from_tracker.as_transform().as_matrix(),
        (D @ sim.T_optical_from_tracker.as_transform() @ E.inverse()).as_matrix(), atol=1e-9)


def test_a_tolerances_file_is_read(tmp_path: Path) -> None:
    f = tmp_path / "tol.toml"
    f.write_text('robot_state_latency_ms = [1.0, 3.0]\ncamera_placement_mm = 5.0\n')
    tol = load_tolerances(f)
    assert tol.robot_state_latency_ms == (1.0, 3.0)
    assert tol.camera_placement_mm == 5.0
    assert tol.flange_marker_error_mm == RigTolerances().flange_marker_error_mm


@pytest.mark.parametrize(("text", "message"), [
    ("robot_state_latency_ms = [3.0, 1.0]\n",
     "robot_state_latency_ms: Value error, [low, high] must have low <= high"),
    ("bogus = 1\n", "bogus: Extra inputs are not permitted"),
    ("robot_state_latency_ms = [1.0, 300.0]\n",
     "robot_state_latency_ms: Input should be less than or equal to 100 (at the band's high end)"),
    ('camera_timestamp = "exposure"\n', "camera_reception_offset_ms / camera_timestamp_jitter_ms need"),
    ("robot_state_latency_ms = [1.0\n", "not TOML"),
])
def test_bad_tolerances_are_one_line(tmp_path: Path, text: str, message: str) -> None:
    f = tmp_path / "tol.toml"
    f.write_text(text)
    with pytest.raises(InputFileError) as info:
        load_tolerances(f)
    assert str(info.value).startswith(f"{f}: ")
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_a_missing_tolerances_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="cannot read"):
        load_tolerances(tmp_path / "none.toml")


def test_the_default_draw_is_a_valid_rig() -> None:
    d = draw_rig(0, RigTolerances())
    assert RigErrorsConfig.model_validate(d.rig_errors.model_dump()) == d.rig_errors


def test_docs_list_the_tolerances_as_the_model_states_them() -> None:
    text = (REPO / "docs" / "bringup.md").read_text()
    assert model_table(TABLE_TITLE, RigTolerances) in text, \
        "docs/bringup.md's rig tolerances table differs from hil/rigcal/draw.py RigTolerances"
