"""The compiled fit of the local change estimators (hil/geometry/_native.c ``local_change``) against
its numpy reference (hil/controller/change_estimate.py ``weighted_numpy``, ``tps_numpy``): every
estimator's change and fallback agree to rounding on deforming skin with markers unseen and far from
the entry; what the kernel declines goes the numpy way; a bad argument is named."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.controller.change_estimate import ChangeEstimator, ChangeFit, estimate_change
from hil.geometry import native
from hil.geometry.transform import RigidTransform
from tests.geometry.strategies import rigid_transforms


def _both(reference: np.ndarray, live: np.ndarray, entry: np.ndarray, estimator: ChangeEstimator,
          sigma_mm: float) -> tuple[ChangeFit | None, ChangeFit | None]:
    """The estimate with the compiled code selected, then with the numpy code."""
    assert native.is_built(), native.native_status()
    previous = native.use_native(True)
    try:
        got = estimate_change(reference, live, entry, estimator, sigma_mm)
        native.use_native(False)
        want = estimate_change(reference, live, entry, estimator, sigma_mm)
    finally:
        native.use_native(previous)
    return got, want


def _same(got: ChangeFit | None, want: ChangeFit | None) -> None:
    assert (got is None) == (want is None)
    if got is None or want is None:
        return
    assert (got.estimator, got.fallback, got.markers) == (want.estimator, want.fallback, want.markers)
    np.testing.assert_allclose(got.T_live_from_ref.R, want.T_live_from_ref.R, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.T_live_from_ref.t, want.T_live_from_ref.t, rtol=0, atol=1e-8)
    assert got.rigid_fre_mm == pytest.approx(want.rigid_fre_mm, rel=1e-9, abs=1e-12)


#: the estimators the kernel compiles
_LOCAL: tuple[ChangeEstimator, ...] = ("weighted", "local-tps")


@settings(max_examples=200, deadline=None)
@given(n=st.integers(3, 14), seed=st.integers(0, 2**32 - 1), T=rigid_transforms(100.0),
       estimator=st.sampled_from(_LOCAL), sigma_mm=st.floats(5.0, 200.0),
       unseen=st.sets(st.integers(0, 13), max_size=3), bend=st.floats(0.0, 0.05))
def test_every_estimator_agrees_with_numpy(n: int, seed: int, T: RigidTransform, estimator: ChangeEstimator,
                                           sigma_mm: float, unseen: set[int], bend: float) -> None:
    rng = np.random.default_rng(seed)
    ref = rng.uniform(-90.0, 90.0, size=(n, 3))
    ref[:, 2] = 0.1 * ref[:, 0] + 0.002 * ref[:, 1] ** 2
    live = T.apply(ref) + bend * np.column_stack([ref[:, 1], ref[:, 0], ref[:, 0] - ref[:, 1]])
    live += rng.normal(0.0, 0.2, size=ref.shape)
    live[sorted(i for i in unseen if i < n)] = np.nan
    entry = rng.uniform(-60.0, 60.0, size=3)
    _same(*_both(ref, live, entry, estimator, sigma_mm))


@pytest.mark.parametrize(("case", "fallback"), [
    ("far", "fewer than 3 markers near the entry: the rigid change of all"),
    ("three", "3 markers seen: the local spline needs 4"),
    ("twin", "local spline: two recorded skin points have the same place on the skin"),
    ("many", ""),
])
def test_fallbacks_and_declined_fits_are_the_numpy_codes(case: str, fallback: str) -> None:
    rng = np.random.default_rng(11)
    ref = rng.uniform(-80.0, 80.0, size=(70 if case == "many" else 6, 3))
    entry = np.zeros(3)
    if case == "far":
        ref[:4] += 2000.0                        # four markers far away: their weight is ~0
    if case == "twin":
        ref[5] = ref[4]                          # two markers at one place: a rigid fit, no spline
    live = RigidTransform.from_rotvec([0.01, 0.02, -0.01], [1.0, 2.0, 3.0]).apply(ref)
    if case == "three":
        live[3:] = np.nan
    got, want = _both(ref, live, entry, "local-tps", 40.0 if case != "far" else 100.0)
    assert want is not None
    assert want.fallback == fallback
    _same(got, want)


def test_bad_arguments_are_named(compiled_geometry: Any) -> None:
    k = compiled_geometry
    ref = np.eye(3) * 10.0
    out = np.empty((3, 3)), np.empty(3), np.empty(3)
    with pytest.raises(ValueError, match="local_change: sigma_mm must be positive and finite"):
        k.local_change(ref, ref, np.zeros(3), 0.0, 1e-3, None, *out)
    with pytest.raises(ValueError, match="tps_row: dimension 0 has length 2, expected 3"):
        k.local_change(ref, ref, np.zeros(3), 10.0, 1e-3, np.zeros(2), *out)
    with pytest.raises(ValueError, match="local_change: argument 2 has 2 rows, the reference 3"):
        k.local_change(ref, ref[:2].copy(), np.zeros(3), 10.0, 1e-3, None, *out)
