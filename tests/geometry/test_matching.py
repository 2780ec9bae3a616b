"""Correspondence-free marker matching: missing/spurious points, outlier markers, symmetry."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.errors import AmbiguousMatchError, DegenerateConfigurationError, GeometryError
from hil.geometry.matching import match_markers
from hil.geometry.registration import register_svd
from hil.geometry.transform import RigidTransform

from .strategies import rigid_transforms

MODEL = np.array(
    [[0.0, 0.0, 0.0], [80.0, 0.0, 5.0], [20.0, 60.0, -3.0], [-30.0, 45.0, 10.0], [55.0, 70.0, 0.0],
     [10.0, -40.0, 8.0]]
)


def asymmetric_layout(rng: np.random.Generator, n: int) -> np.ndarray:
    """Marker layouts whose pairwise distances are >= 15 mm and differ from each other by >= 2 mm."""
    while True:
        pts = rng.uniform(-80, 80, size=(n, 3)) * [1.0, 1.0, 0.4]
        d = np.array([np.linalg.norm(a - b) for a, b in itertools.combinations(pts, 2)])
        diffs = np.abs(d[:, None] - d[None, :])[np.triu_indices(len(d), 1)]
        if d.min() >= 15.0 and diffs.min() >= 2.0:
            return pts


@settings(max_examples=100)
@given(st.integers(4, 6), rigid_transforms(), st.integers(0, 2**32 - 1))
def test_survives_one_missing_and_one_spurious_point(n: int, T: RigidTransform, seed: int) -> None:
    rng = np.random.default_rng(seed)
    model = asymmetric_layout(rng, n)
    true_measured = T.apply(model) + rng.normal(scale=0.2, size=model.shape)
    missing = int(rng.integers(n))
    while True:  # a spurious blob well away from every real marker
        spur = T.apply(rng.uniform(-80, 80, size=3) * [1.0, 1.0, 0.3])
        if np.min(np.linalg.norm(true_measured - spur, axis=1)) > 10.0:
            break
    visible = [i for i in range(n) if i != missing]
    measured = np.vstack([true_measured[visible], spur])
    perm = rng.permutation(len(measured))
    measured = measured[perm]
    where = {int(p): k for k, p in enumerate(perm)}  # original row -> shuffled row

    match = match_markers(measured, model)

    expected = {model_i: where[row] for row, model_i in enumerate(visible)}
    if n == 4 and match.ambiguous:
        # only 3 markers visible: a spurious blob can complete a congruent triangle by chance.
        # That must be flagged, never silently chosen, and the truth must be among the options.
        assert expected in [match.model_to_measured, *match.alternatives]
        return
    assert match.model_to_measured == expected
    assert match.excluded_model == (missing,)
    assert match.spurious_measured == (where[len(visible)],)
    assert not match.ambiguous
    assert set(match.residuals_mm) == set(visible)
    assert max(match.residuals_mm.values()) < 1.5
    lsq = register_svd(measured[[expected[i] for i in visible]], model[visible]).T_fixed_from_moving
    assert match.T_measured_from_model.is_close(lsq, atol_mm=1e-9, atol_rad=1e-9)


def test_outlier_marker_is_excluded_when_the_rest_agree() -> None:
    T = RigidTransform.from_rotvec([0.4, -1.2, 2.0], [100.0, -50.0, 900.0])
    measured = T.apply(MODEL)
    measured[4] += [6.0, 0.0, 0.0]  # marker 4 slid on the skin
    match = match_markers(measured, MODEL, tolerance_mm=2.0)
    assert match.model_to_measured == {0: 0, 1: 1, 2: 2, 3: 3, 5: 5}
    assert match.excluded_model == (4,)
    assert match.spurious_measured == (4,)
    assert match.excluded_distance_mm == pytest.approx({4: 6.0})
    assert match.fre_rms_mm < 1e-9
    assert match.T_measured_from_model.is_close(T, 1e-9, 1e-9)


def test_symmetric_layout_is_flagged_not_silently_picked() -> None:
    square = np.array([[0.0, 0.0, 0.0], [60.0, 0.0, 0.0], [60.0, 40.0, 0.0], [0.0, 40.0, 0.0]])
    T = RigidTransform.from_rotvec([0.1, 0.2, 0.3], [10.0, 20.0, 500.0])
    match = match_markers(T.apply(square), square)
    assert match.ambiguous
    # a rectangle maps onto itself by 180-degree turns about three axes: 3 rival assignments
    assert len(match.alternatives) == 3
    with pytest.raises(AmbiguousMatchError):
        match_markers(T.apply(square), square, strict=True)
    # near-symmetric (0.3 mm off a rectangle) with measurement noise: still flagged
    rng = np.random.default_rng(0)
    near = square + np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, -0.2, 0.0], [0.0, 0.0, 0.0]])
    noisy = T.apply(near) + rng.normal(scale=0.1, size=near.shape)
    assert match_markers(noisy, near).ambiguous
    # break the symmetry by 10 mm: unambiguous and correct
    skew = square + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    clear = match_markers(T.apply(skew), skew, strict=True)
    assert not clear.ambiguous
    assert clear.model_to_measured == {0: 0, 1: 1, 2: 2, 3: 3}


def test_no_consistent_match_raises() -> None:
    rng = np.random.default_rng(9)
    with pytest.raises(GeometryError, match="no consistent match"):
        match_markers(rng.uniform(-500, 500, size=(5, 3)), MODEL, tolerance_mm=0.5)
    with pytest.raises(GeometryError):
        match_markers(MODEL[:2], MODEL)
    with pytest.raises(GeometryError):
        match_markers(MODEL[:4], MODEL, min_matched=5)


def test_bad_inputs() -> None:
    with pytest.raises(DegenerateConfigurationError):
        match_markers(MODEL, np.outer(np.arange(4.0), [1.0, 0.0, 0.0]) * 20)
    with pytest.raises(GeometryError):
        match_markers(np.vstack([MODEL, [np.nan, 0, 0]]), MODEL)
    with pytest.raises(GeometryError):
        match_markers(MODEL, MODEL, tolerance_mm=0.0)
    with pytest.raises(GeometryError):
        match_markers(MODEL, MODEL, min_matched=2)
