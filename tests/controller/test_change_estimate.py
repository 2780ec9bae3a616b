"""The change estimators of COMPENSATE (issue 41): rigid, weighted, local-tps; fallbacks; the gate's
shape check and the deformation monitor."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.controller.change_estimate import entry_weights, estimate_change
from hil.controller.compensation import deformation_out_of_bounds
from hil.controller.config import CompensationConfig, GateConfig
from hil.controller.gate import gate_measures
from hil.geometry.transform import RigidTransform

#: six skin markers around an entry at the origin (optical frame, mm), roughly on a plane
REF = np.array([[60.0, 10.0, 2.0], [-55.0, 20.0, 1.0], [10.0, 70.0, -3.0], [-20.0, -65.0, 0.0],
                [75.0, -50.0, 4.0], [-70.0, -30.0, -2.0]])
ENTRY = np.array([3.0, -4.0, 0.5])


def _field(p: np.ndarray) -> np.ndarray:
    """A smooth non-rigid displacement: more motion on one side, as a breathing abdomen."""
    return np.column_stack([0.01 * p[:, 1], 0.02 * p[:, 0], 4.0 + 0.03 * p[:, 0] - 0.01 * p[:, 1]])


@settings(max_examples=80, deadline=None)
@given(st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3),
       st.lists(st.floats(-40, 40), min_size=3, max_size=3),
       st.sampled_from(["rigid", "weighted", "local-tps"]))
def test_a_rigid_motion_is_recovered_by_every_estimator(rv: list[float], t: list[float],
                                                        estimator: str) -> None:
    T = RigidTransform.from_rotvec(rv, t)
    fit = estimate_change(REF, T.apply(REF), ENTRY, estimator, 60.0)  # type: ignore[arg-type]
    assert fit is not None
    assert fit.estimator == estimator
    assert fit.fallback == ""
    assert fit.T_live_from_ref.is_close(T, atol_mm=1e-6, atol_rad=1e-8)
    assert fit.rigid_fre_mm < 1e-6
    assert np.all(fit.residuals_mm < 1e-6)


def test_on_a_deforming_body_the_local_estimators_follow_the_entry() -> None:
    live = REF + _field(REF)
    entry = np.array([45.0, 40.0, 1.0])           # off the markers' centroid, where averaging errs
    truth = entry + _field(entry[None, :])[0]
    errors = {}
    for e in ("rigid", "weighted", "local-tps"):
        fit = estimate_change(REF, live, entry, e, 60.0)  # type: ignore[arg-type]
        assert fit is not None
        errors[e] = float(np.linalg.norm(fit.T_live_from_ref.apply(entry) - truth))
        assert fit.rigid_fre_mm > 0.3            # every fit reports the same deformation monitor
    # the spline reproduces an affine field at the entry (to the markers' out-of-plane spread); the
    # rigid fit averages it
    assert errors["rigid"] > 0.5
    assert errors["local-tps"] < 0.1 * errors["rigid"]
    assert errors["weighted"] < errors["rigid"]


def test_unseen_markers_are_left_out_and_fallbacks_are_named() -> None:
    live = REF + _field(REF)
    seen = live.copy()
    seen[[1, 4, 5]] = np.nan
    fit = estimate_change(REF, seen, ENTRY, "local-tps", 60.0)
    assert fit is not None
    assert fit.markers == 3
    assert fit.estimator == "weighted"
    assert "local spline needs 4" in fit.fallback
    assert np.isnan(fit.residuals_mm[[1, 4, 5]]).all()
    assert np.isfinite(fit.residuals_mm[[0, 2, 3]]).all()
    # markers all far from the entry: no three carry weight, the rigid change of all is used
    far = estimate_change(REF, live, np.array([5000.0, 0.0, 0.0]), "weighted", 10.0)
    assert far is not None
    assert far.estimator == "rigid"
    assert "near the entry" in far.fallback
    seen[2] = np.nan
    assert estimate_change(REF, seen, ENTRY, "rigid", 60.0) is None      # two markers: unknown


def test_collinear_markers_give_no_change() -> None:
    line = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0], [30.0, 0.0, 0.0]])
    assert estimate_change(line, line + 1.0, ENTRY, "local-tps", 60.0) is None


def test_entry_weights() -> None:
    w = entry_weights(np.array([[0.0, 0.0, 0.0], [60.0, 0.0, 0.0]]), np.zeros(3), 60.0)
    assert w == pytest.approx([1.0, math.exp(-1.0)])


def test_the_deformation_monitor_pauses_beyond_its_bound() -> None:
    cfg = CompensationConfig(deformation_bound_mm=1.0)
    calm = estimate_change(REF, REF + 0.1 * _field(REF), ENTRY, "rigid", 60.0)
    cough = estimate_change(REF, REF + 3.0 * _field(REF), ENTRY, "rigid", 60.0)
    assert calm is not None
    assert cough is not None
    assert deformation_out_of_bounds(calm, cfg) is None
    why = deformation_out_of_bounds(cough, cfg)
    assert why is not None
    assert "no longer move as one body" in why
    assert f"{cough.rigid_fre_mm:.1f} mm" in why
    assert deformation_out_of_bounds(None, cfg) is None


def test_the_gate_wants_the_shape_back_not_only_the_average() -> None:
    cfg = GateConfig(tolerance_mm=1.5, marker_tolerance_mm=3.0, shape_tolerance_mm=0.5)
    shifted = gate_measures(REF, REF + np.array([0.5, 0.5, 0.5]))          # rigid, small: back
    assert shifted.problem(cfg) is None
    assert shifted.shape_mm < 1e-6
    bent = REF.copy()
    bent[0] += [0.0, 0.0, 2.6]                                             # one marker off
    m = gate_measures(REF, bent)
    assert m.rms_mm < 1.5
    assert m.max_marker_mm == pytest.approx(2.6)
    why = m.problem(cfg)
    assert why is not None
    assert "shape" in why
    assert m.problem(GateConfig(tolerance_mm=1.5, marker_tolerance_mm=2.0, shape_tolerance_mm=None)) == (
        "a marker 2.60 mm from its reference (tolerance 2.0 mm)")
    assert m.problem(GateConfig(tolerance_mm=1.5, marker_tolerance_mm=None, shape_tolerance_mm=None)) is None
    assert m.problem(GateConfig(tolerance_mm=1.2, marker_tolerance_mm=None, shape_tolerance_mm=None)) == (
        "a marker 2.60 mm from its reference (tolerance 2.4 mm)")   # None: twice tolerance_mm
    few = gate_measures(REF, np.where(np.arange(6)[:, None] < 2, REF, np.nan))
    assert few.problem(cfg) == "only 2 reference markers seen (need 3)"
