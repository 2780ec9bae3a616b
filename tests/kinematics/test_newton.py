"""The servo step's inverse kinematics (hil.kinematics.ur.ur_newton_ik): the compiled Newton steps
(hil/geometry/_native.c) agree with the numpy reference to rounding, say "no solution" where it
does, leave non-finite input to the numpy code, and reach the pose they were asked for."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hil.errors import GeometryError
from hil.geometry import native
from hil.geometry.transform import RigidTransform
from hil.kinematics.ur import _dh_array, ur_forward, ur_newton_ik, ur_newton_ik_numpy

#: the simulated arm's settings (drivers/sim/robot.py)
SETTINGS: dict[str, Any] = {"iterations": 6, "tol_mm": 1e-6, "tol_rad": 1e-9, "min_det_mm3": 1e3,
                            "max_jump_rad": 0.6}
#: a UR3 pose away from its singularities (rad)
Q_HOME = np.array([0.3, -1.2, 1.4, -1.8, -1.5, 0.4])


def _both(T: RigidTransform, q_seed: np.ndarray, model: str = "ur3",
          **overrides: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(compiled, numpy): the compiled code selected for the first call whatever the test's
    fixtures (hypothesis runs many inputs per fixture), the previous selection restored."""
    kw = {**SETTINGS, **overrides}
    assert native.is_built(), native.native_status()
    previous = native.use_native(True)
    try:
        got = ur_newton_ik(T, q_seed, model, **kw)
    finally:
        native.use_native(previous)
    return got, ur_newton_ik_numpy(T, q_seed, model, **kw)


def _compiled_status(T: RigidTransform, q_seed: np.ndarray, model: str) -> int:
    """What the compiled code itself returns (0 solved, 1 no solution, -1 left to numpy)."""
    previous = native.use_native(True)
    try:
        k = native.active()
        assert k is not None
        c = SETTINGS
        status: int = k.ur_newton(_dh_array(model), T.R, T.t, q_seed, c["iterations"], c["tol_mm"],
                                  c["tol_rad"], c["min_det_mm3"], c["max_jump_rad"], np.empty(6))
    finally:
        native.use_native(previous)
    return status


steps = arrays(np.float64, 6, elements=st.floats(-0.05, 0.05))
offsets = arrays(np.float64, 6, elements=st.floats(-0.8, 0.8))


@settings(max_examples=300, deadline=None)
@given(offsets, steps, st.sampled_from(["ur3", "ur3e"]))
def test_a_servo_step_agrees_with_numpy_and_reaches_the_pose(offset: np.ndarray, step: np.ndarray,
                                                             model: str) -> None:
    q_seed = Q_HOME + offset
    T = ur_forward(q_seed + step, model)
    got, ref = _both(T, q_seed, model)
    assert _compiled_status(T, q_seed, model) in (0, 1)   # decided in compiled code, not by numpy
    assert (got is None) == (ref is None)
    if got is None or ref is None:
        return
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    reached = ur_forward(got, model)
    assert float(np.linalg.norm(reached.t - T.t)) < 1e-6
    np.testing.assert_allclose(reached.R, T.R, rtol=0, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(arrays(np.float64, 6, elements=st.floats(-np.pi, np.pi)),
       arrays(np.float64, 6, elements=st.floats(-1.5, 1.5)))
def test_far_targets_and_flips_agree_with_numpy(q_seed: np.ndarray, jump: np.ndarray) -> None:
    """Large steps: whatever numpy finds (a solution, a flip refused, no convergence, a
    singularity), the compiled code finds too - or hands the case to numpy (same result)."""
    got, ref = _both(ur_forward(q_seed + jump), q_seed)
    assert (got is None) == (ref is None)
    if got is not None and ref is not None:
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


def test_a_jump_over_the_limit_is_no_solution(compiled_geometry: Any) -> None:
    q_target = Q_HOME + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.3])
    assert ur_newton_ik(ur_forward(q_target), Q_HOME, **{**SETTINGS, "max_jump_rad": 0.2}) is None
    got = ur_newton_ik(ur_forward(q_target), Q_HOME, **SETTINGS)
    assert got is not None
    np.testing.assert_allclose(got, q_target, rtol=0, atol=1e-9)


def test_out_of_iterations_is_no_solution(compiled_geometry: Any) -> None:
    T = ur_forward(Q_HOME + 0.04)
    assert ur_newton_ik(T, Q_HOME, **{**SETTINGS, "iterations": 1}) is None
    assert ur_newton_ik_numpy(T, Q_HOME, **{**SETTINGS, "iterations": 1}) is None


def test_a_singular_seed_is_no_solution(compiled_geometry: Any) -> None:
    """Wrist singularity (q5 = 0: joints 4 and 6 aligned): |det J| is 0."""
    q = Q_HOME.copy()
    q[4] = 0.0
    T = ur_forward(q + 0.01)
    got, ref = _both(T, q)
    assert got is None
    assert ref is None


def test_the_seed_itself_is_returned_at_once(compiled_geometry: Any) -> None:
    got = ur_newton_ik(ur_forward(Q_HOME), Q_HOME, **SETTINGS)
    assert got is not None
    np.testing.assert_array_equal(got, Q_HOME)


def test_a_non_finite_seed_is_a_typed_error(compiled_geometry: Any) -> None:
    with pytest.raises(GeometryError, match="q_seed_rad must be 6 finite"):
        ur_newton_ik(ur_forward(Q_HOME), np.array([0.0, np.nan, 0, 0, 0, 0]), **SETTINGS)


def test_non_finite_input_goes_the_numpy_way(compiled_geometry: Any) -> None:
    """The compiled code declines (-1), and ur_newton_ik then runs the numpy code. (Through the
    public function the target is a checked transform; this is the C contract.)"""
    k, out, dh = compiled_geometry, np.empty(6), _dh_array("ur3")
    inf_t = np.array([np.inf, 0.0, 0.0])
    assert k.ur_newton(dh, np.eye(3), inf_t, Q_HOME, 6, 1e-6, 1e-9, 1e3, 0.6, out) == -1
    assert k.ur_newton(dh, np.full((3, 3), np.nan), np.zeros(3), Q_HOME, 6, 1e-6, 1e-9, 1e3, 0.6, out) == -1


def test_bad_buffers_name_the_argument(compiled_geometry: Any) -> None:
    k, out, dh = compiled_geometry, np.empty(6), _dh_array("ur3")
    with pytest.raises(ValueError, match="dh: dimension 0 has length 5"):
        k.ur_newton(dh[:5].copy(), np.eye(3), np.zeros(3), Q_HOME, 6, 1e-6, 1e-9, 1e3, 0.6, out)
    with pytest.raises(TypeError, match="q_seed: expected float64"):
        k.ur_newton(dh, np.eye(3), np.zeros(3), Q_HOME.astype(np.float32), 6, 1e-6, 1e-9, 1e3, 0.6, out)
    ro = np.empty(6)
    ro.setflags(write=False)
    with pytest.raises(TypeError, match="q_out: expected a writable"):
        k.ur_newton(dh, np.eye(3), np.zeros(3), Q_HOME, 6, 1e-6, 1e-9, 1e3, 0.6, ro)
