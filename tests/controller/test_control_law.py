"""COMPENSATE's per-pair control law in compiled code (``filter_feed``, ``filter_pose`` and
``tcp_setpoint`` in hil/geometry/_native.c) against its numpy reference: the motion filter's step
about the entry point (``MotionFilter.update_about``), its extrapolated pose
(``MotionFilter.estimate``) and the tracking setpoint with its velocity
(``Estimate.tracking_setpoint``) agree to rounding; what the compiled code declines goes to the
numpy code, which raises the same typed error either way."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hil.controller.compensation import MotionFilter
from hil.controller.estimate import Estimate
from hil.errors import GeometryError
from hil.geometry import native
from hil.geometry.transform import RigidTransform
from tests.controller.fakes import chain_estimate
from tests.geometry.strategies import rigid_transforms

T0_NS = 1_000_000_000


@st.composite
def changes(draw: st.DrawFn) -> RigidTransform:
    """A measured patient change: rotation up to 2.5 rad (away from pi, where the rotation
    vector's axis sign is a matter of rounding in any code), translation up to 200 mm."""
    axis = draw(arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)))
    n = float(np.linalg.norm(axis))
    angle = draw(st.floats(0.0, 2.5))
    rv = np.zeros(3) if n < 1e-3 else axis / n * angle
    t = draw(arrays(np.float64, 3, elements=st.floats(-200.0, 200.0)))
    return RigidTransform.from_rotvec(rv, t)


dts_s = st.floats(0.001, 0.1)


@pytest.fixture
def numpy_geometry() -> Iterator[None]:
    """The numpy reference selected for the test, the previous selection restored after."""
    previous = native.use_native(False)
    yield
    native.use_native(previous)


def _fed(samples: list[RigidTransform], dts: list[float], T_center: RigidTransform, alpha: float,
         beta: float, compiled: bool) -> MotionFilter:
    """A filter fed ``samples`` about ``T_center``, ``dts`` apart, with the chosen code."""
    previous = native.use_native(compiled)
    try:
        f = MotionFilter(alpha, beta)
        t_ns = T0_NS
        for T, dt in zip(samples, [0.0, *dts], strict=True):
            t_ns += round(dt * 1e9)
            f.update_about(T, T_center, t_ns)
        return f
    finally:
        native.use_native(previous)


def _assert_vec_close(a: np.ndarray, b: np.ndarray, scale: float = 1.0) -> None:
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * scale)


@settings(max_examples=300, deadline=None)
@given(st.lists(changes(), min_size=2, max_size=4), st.lists(dts_s, min_size=3, max_size=3),
       rigid_transforms(), st.floats(0.05, 1.0), st.floats(0.0, 1.0))
def test_filter_feed_agrees_with_numpy(samples: list[RigidTransform], dts: list[float],
                                       T_center: RigidTransform, alpha: float, beta: float) -> None:
    dts = dts[:len(samples) - 1]
    fc = _fed(samples, dts, T_center, alpha, beta, compiled=True)
    fn = _fed(samples, dts, T_center, alpha, beta, compiled=False)
    (xc, vc), (xn, vn) = fc.vectors(), fn.vectors()
    _assert_vec_close(xc, xn, 1e3)
    _assert_vec_close(vc, vn, 1e6)   # beta / dt magnifies rounding by up to 1e3


@settings(max_examples=200, deadline=None)
@given(st.lists(changes(), min_size=2, max_size=3), st.lists(dts_s, min_size=2, max_size=2),
       st.floats(0.0, 0.2), st.floats(0.0, 0.1))
def test_filter_pose_agrees_with_numpy(samples: list[RigidTransform], dts: list[float], ahead_s: float,
                                       max_horizon_s: float) -> None:
    f = _fed(samples, dts[:len(samples) - 1], RigidTransform.identity(), 0.6, 0.2, compiled=False)
    t_ns = T0_NS + round(sum(dts[:len(samples) - 1]) * 1e9) + round(ahead_s * 1e9)
    with_compiled = native.use_native(True)
    try:
        Tc = f.estimate(t_ns, max_horizon_s)
    finally:
        native.use_native(with_compiled)
    previous = native.use_native(False)
    try:
        Tn = f.estimate(t_ns, max_horizon_s)
    finally:
        native.use_native(previous)
    np.testing.assert_allclose(Tc.R, Tn.R, rtol=0, atol=1e-12)
    _assert_vec_close(Tc.t, Tn.t, 1e3)


def _setpoint(est: Estimate, t_ns: int, max_horizon_s: float, step_s: float,
              compiled: bool) -> tuple[RigidTransform, np.ndarray, np.ndarray]:
    previous = native.use_native(compiled)
    try:
        return est.tracking_setpoint(t_ns, max_horizon_s, step_s)
    finally:
        native.use_native(previous)


@settings(max_examples=300, deadline=None)
@given(rigid_transforms(), rigid_transforms(), rigid_transforms(), rigid_transforms(),
       st.lists(changes(), min_size=2, max_size=2), dts_s, st.floats(0.0, 0.05),
       st.sampled_from([0.0, 0.01, 0.003]))
def test_tracking_setpoint_agrees_with_numpy(T_ro: RigidTransform, T_rt: RigidTransform,
                                             T_center: RigidTransform, T_bias: RigidTransform,
                                             samples: list[RigidTransform], dt: float, max_horizon_s: float,
                                             step_s: float) -> None:
    est = chain_estimate(T_ro, T_rt, T_center, T_bias)
    # slow changes (as the filter sees them): the velocity's difference is then well-conditioned
    small = [RigidTransform.from_rotvec(T.as_rotvec() * 0.01, T.t * 0.01) for T in samples]
    est.filter = _fed(small, [dt], T_center, 0.6, 0.2, compiled=False)
    t_exp = T0_NS + round(dt * 1e9)
    Dc, vc, wc = _setpoint(est, t_exp, max_horizon_s, step_s, compiled=True)
    Dn, vn, wn = _setpoint(est, t_exp, max_horizon_s, step_s, compiled=False)
    np.testing.assert_allclose(Dc.R, Dn.R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(Dc.t, Dn.t, rtol=0, atol=1e-9)    # mm, poses up to a few metres
    if step_s == 0.0:
        assert vc.tolist() == [0.0, 0.0, 0.0]
        assert wc.tolist() == [0.0, 0.0, 0.0]
        assert vn.tolist() == [0.0, 0.0, 0.0]
        assert wn.tolist() == [0.0, 0.0, 0.0]
    # a difference over step_s divides the poses' rounding by it
    np.testing.assert_allclose(vc, vn, rtol=0, atol=1e-9 / max(step_s, 1e-3))
    np.testing.assert_allclose(wc, wn, rtol=0, atol=1e-11 / max(step_s, 1e-3))


def test_the_compiled_setpoint_is_the_one_used(compiled_geometry: Any) -> None:
    """The compiled call itself succeeds on a typical pair (so the estimate's answer is its),
    and gives the pose the numpy chain composes."""
    est = chain_estimate(RigidTransform.from_rotvec((0.1, -0.2, 0.3), (400.0, -50.0, 300.0)),
                    RigidTransform.from_rotvec((3.0, 0.1, 0.0), (300.0, 100.0, 200.0)),
                    RigidTransform.from_translation((10.0, 20.0, 500.0)),
                    RigidTransform.from_rotvec((0.001, 0.0, 0.0), (0.2, -0.1, 0.0)))
    est.filter.update_about(RigidTransform.from_rotvec((0.01, 0.0, 0.0), (1.0, 2.0, 3.0)), est.T_center,
                            T0_NS)
    est.filter.update_about(RigidTransform.from_rotvec((0.012, 0.0, 0.0), (1.5, 2.0, 3.0)), est.T_center,
                            T0_NS + 33_000_000)
    x, v = est.filter.vectors()
    L, R = est._chain_ends()
    out = np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3)
    assert compiled_geometry.tcp_setpoint(x, v, 0.0, 0.01, 0.01, L.R, L.t, R.R, R.t, *out) == 0
    D, vel, w = est.tracking_setpoint(T0_NS + 33_000_000, 0.1, 0.01)
    assert D.R.tolist() == out[0].tolist()
    assert D.t.tolist() == out[1].tolist()
    assert vel.tolist() == out[2].tolist()
    assert w.tolist() == out[3].tolist()
    expected = est.desired_tcp_robot_local(RigidTransform(*_pose(x)))
    np.testing.assert_allclose(D.t, expected.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(D.R, expected.R, rtol=0, atol=1e-12)
    assert float(vel[0]) > 0.0   # the change moves +x at about 15 mm/s


def _pose(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return RigidTransform.from_rotvec(x[3:]).R, x[:3]


@pytest.mark.parametrize("compiled", [True, False])
def test_an_overflowing_state_raises_the_same_error(compiled: bool, compiled_geometry: Any) -> None:
    """Rotation vectors whose squared norm overflows: the compiled code declines them; numpy
    answers where the norm itself is finite and raises where it is not, in either selection."""
    f = MotionFilter(0.6, 0.2)
    f.update(RigidTransform.identity(), T0_NS)
    out = np.empty((3, 3)), np.empty(3)
    f._v = np.array([0.0, 0.0, 0.0, 1e308, 1e308, 0.0])   # |rv| = 1.4e308: finite
    assert compiled_geometry.filter_pose(*f.vectors(), 1.0, *out) == -1
    native.use_native(False)
    expected = f.estimate(T0_NS + 1_000_000_000, 1.0)
    native.use_native(compiled)
    got = f.estimate(T0_NS + 1_000_000_000, 1.0)
    assert got.R.tolist() == expected.R.tolist()
    assert got.t.tolist() == expected.t.tolist()
    f._v = np.array([0.0, 0.0, 0.0, 1.5e308, 1.5e308, 1.5e308])   # |rv| overflows
    with pytest.raises(GeometryError, match="overflows a float"):
        f.estimate(T0_NS + 1_000_000_000, 1.0)


def test_a_non_finite_centre_is_declined(compiled_geometry: Any) -> None:
    x, v = np.zeros(6), np.zeros(6)
    R, t = np.eye(3), np.zeros(3)
    assert compiled_geometry.filter_feed(R, t, R, np.array([np.nan, 0.0, 0.0]), x, v, 0.01, 0.5, 0.1) == -1
    assert compiled_geometry.filter_feed(R, t, R, t, x, v, 0.0, 0.5, 0.1) == -1   # dt must be > 0
    assert x.tolist() == [0.0] * 6
    assert v.tolist() == [0.0] * 6


def test_a_filter_fed_in_the_past_keeps_its_state(compiled_geometry: Any) -> None:
    f = MotionFilter(0.6, 0.2)
    f.update_about(RigidTransform.from_translation((1.0, 0.0, 0.0)), RigidTransform.identity(), T0_NS)
    f.update_about(RigidTransform.from_translation((5.0, 0.0, 0.0)), RigidTransform.identity(), T0_NS)
    x, v = f.vectors()
    assert x.tolist() == [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert v.tolist() == [0.0] * 6


def test_nothing_fed_raises(numpy_geometry: None) -> None:
    est = chain_estimate(*[RigidTransform.identity()] * 4)
    with pytest.raises(GeometryError, match="no sample yet"):
        est.tracking_setpoint(T0_NS, 0.1, 0.01)
    native.use_native(True)
    with pytest.raises(GeometryError, match="no sample yet"):
        est.tracking_setpoint(T0_NS, 0.1, 0.01)


def test_bad_buffers_name_the_argument(compiled_geometry: Any) -> None:
    k = compiled_geometry
    R, t, x = np.eye(3), np.zeros(3), np.zeros(6)
    with pytest.raises(ValueError, match="x: dimension 0 has length 5, expected 6"):
        k.filter_feed(R, t, R, t, np.zeros(5), x, 0.01, 0.5, 0.1)
    with pytest.raises(TypeError, match="v: expected a writable"):
        k.filter_feed(R, t, R, t, x, _readonly(6), 0.01, 0.5, 0.1)
    with pytest.raises(TypeError, match="R_out: expected a writable"):
        k.filter_pose(x, x, 0.0, _readonly(3, 3), np.empty(3))
    with pytest.raises(TypeError, match="w_out: expected float64 items"):
        k.tcp_setpoint(x, x, 0.0, 0.0, 0.0, R, t, R, t, np.empty((3, 3)), np.empty(3), np.empty(3),
                       np.empty(3, dtype=np.float32))
    with pytest.raises(ValueError, match="LR: expected 2 dimension"):
        k.tcp_setpoint(x, x, 0.0, 0.0, 0.0, t, t, R, t, np.empty((3, 3)), np.empty(3), np.empty(3),
                       np.empty(3))


def _readonly(*shape: int) -> np.ndarray:
    a = np.zeros(shape)
    a.setflags(write=False)
    return a
