"""The compiled kernel (hil/vision/_kernel.c: ring edges, robust ellipse fits, ring check, the
stereo stage's plane-normal correction, DLT and ray gaps) against the numpy reference it replaces.

Tolerances (the kernel does the reference's arithmetic in the same order except for a few sums --
numpy's pairwise sums and BLAS products -- and libm's cos/sin/acos, so the two differ by rounding):
- decisions equal: edge masks, ring ``ok``, valid fractions, fit ``good``, the inlier set of every
  fit, the rings accepted by the ring check, the markers paired, re-acquisitions and losses;
- edge points within 1e-9 px; conics within 1e-9 (unit Frobenius norm); centres, semi-axes and
  residuals within 1e-9 px; major-axis directions within 1e-9 rad modulo pi (where a - b > 1e-3 a:
  a near-circle's angle is rounding noise, +-pi/2 apart for a circle); on random point sets
  (12-48 points, up to 8 outliers) the fits within 1e-9 relative or the larger of 1e-9 and 200x
  the numpy code's own change when the points are reversed (an ill-conditioned fit -- a tiny
  ellipse with few noisy points, points exactly on an ellipse -- moves by more than 1e-9 under
  reordering alone);
- DLT points (the null vector by one-sided Jacobi rotations, numpy by LAPACK's SVD) within
  1e-11 x depth x max(depth / baseline, 1) mm;
- the stereo stage's ideal centres and affine maps of distortion within 1e-9 px (bit-equal in
  practice; a point whose undistortion does not converge is flagged and left to OpenCV), conics
  through those maps within 1e-12;
- ray gaps within 1e-9 relative; the plane-normal correction (random circles seen by the rig,
  each view's normal and centre perturbed): the same corrected pairs, centres within
  1e-9 px and normals within 1e-9;
- full-frame 3D points within 1e-8 mm; tracked 3D points within 1e-6 mm (the tracker carries
  last-digit differences from pair to pair through its predictions).
"""

from __future__ import annotations

import gc
import math
import os
import sys
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.geometry.triangulation import triangulate_dlt
from hil.vision import kernel, stereo
from hil.vision.camera_model import StereoCalibration
from hil.vision.conics import circle_image_conic
from hil.vision.detect import (
    DetectParams,
    RingDetection,
    _ring_check,
    _ring_check_kernel,
    begin_search,
    detect_rings_multi,
)
from hil.vision.ellipse import ellipse_from_conic, fit_ellipse_arrays_numpy, fit_ellipse_arrays_used
from hil.vision.render import RenderedPair, RenderOptions, RingMarker3D, render_stereo
from hil.vision.ring_edges import RingEdges, RingSeeds, ring_edges_multi, ring_edges_multi_numpy
from hil.vision.stereo import match_and_triangulate
from hil.vision.tracking import MarkerTracker, TrackingParams

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools" / "benchmarks"))
from vision_sequence import breathing_sequence, scaled_rig

PX_TOL = 1e-9
DP = DetectParams()


@pytest.fixture
def compiled() -> Iterator[None]:
    """The compiled kernel selected for the test (the previous selection restored after)."""
    assert kernel._module is not None, kernel.kernel_status()
    previous = kernel.use_kernel(True)
    yield
    kernel.use_kernel(previous)


def test_the_kernel_is_built_and_selected_by_default() -> None:
    assert kernel._module is not None, kernel.kernel_status()
    numpy_asked = os.environ.get("HIL_VISION_KERNEL", "").lower() == "numpy"
    assert kernel.kernel_status() == ("numpy (selected)" if numpy_asked else "compiled kernel")


def _sequence_pairs(count: int) -> list[RenderedPair]:
    cal = scaled_rig(1920)
    layout, offsets, hidden = breathing_sequence(8, 90, 7)
    rng = np.random.default_rng(1007)
    out = []
    for k in range(count):
        markers = [RingMarker3D(m.center_mm + offsets[k], m.normal, marker_id=m.marker_id)
                   for m in layout if not (m.marker_id == 0 and k in hidden)]
        out.append(render_stereo(cal, markers, RenderOptions(noise_sigma=2.0), rng))
    return out


@pytest.fixture(scope="module")
def pairs() -> list[RenderedPair]:
    return _sequence_pairs(12)


def _assert_same_edges(a: RingEdges, b: RingEdges) -> None:
    np.testing.assert_array_equal(a.ok, b.ok)
    np.testing.assert_array_equal(a.mo, b.mo)
    np.testing.assert_array_equal(a.mi, b.mi)
    np.testing.assert_array_equal(a.frac, b.frac)
    np.testing.assert_array_equal(a.dark_on_light, b.dark_on_light)
    for u, v in ((a.xo, b.xo), (a.yo, b.yo), (a.xi, b.xi), (a.yi, b.yi)):
        np.testing.assert_allclose(u, v, rtol=0, atol=PX_TOL)


def _assert_same_fits(
    X: np.ndarray, Y: np.ndarray, M: np.ndarray, tol: float = PX_TOL, rtol: float = 0.0
) -> None:
    with np.errstate(all="ignore"):  # the reference on a degenerate set (not an ellipse) warns
        ref, ref_used = fit_ellipse_arrays_numpy(X, Y, M)
    got, used = fit_ellipse_arrays_used(X, Y, M)
    np.testing.assert_array_equal(got.good, ref.good)
    g = ref.good
    np.testing.assert_array_equal(used[g], ref_used[g])
    np.testing.assert_array_equal(got.n_points[g], ref.n_points[g])
    np.testing.assert_allclose(got.conic[g], ref.conic[g], rtol=0, atol=tol)
    for u, v in ((got.center_px, ref.center_px), (got.a_px, ref.a_px), (got.b_px, ref.b_px),
                 (got.residual_rms_px, ref.residual_rms_px)):
        np.testing.assert_allclose(u[g], v[g], rtol=rtol, atol=tol)
    # the major axis' direction (modulo pi), where there is one: a near-circle's is rounding noise
    e = g & (ref.a_px - ref.b_px > 1e-3 * ref.a_px)
    turn = np.mod(got.angle_rad[e] - ref.angle_rad[e] + math.pi / 2, math.pi) - math.pi / 2
    np.testing.assert_allclose(turn, 0.0, rtol=0, atol=tol)


@pytest.mark.usefixtures("compiled")
def test_edges_and_fits_equal_the_numpy_code_on_the_bench_sequence(pairs: list[RenderedPair]) -> None:
    n_rings = 0
    for p in pairs:
        parts = [(s.frame, s.seeds) for s in (begin_search(p.left, DP), begin_search(p.right, DP))]
        ref = ring_edges_multi_numpy(parts, DP.n_rays, DP.min_contrast, DP.min_valid_fraction)
        got = ring_edges_multi(parts, DP.n_rays, DP.min_contrast, DP.min_valid_fraction)
        _assert_same_edges(got, ref)
        idx = np.nonzero(ref.ok)[0]
        n_rings += idx.size
        X, Y = np.concatenate([ref.xo[idx], ref.xi[idx]]), np.concatenate([ref.yo[idx], ref.yi[idx]])
        _assert_same_fits(X, Y, np.concatenate([ref.mo[idx], ref.mi[idx]]))
        fits, _ = fit_ellipse_arrays_numpy(X, Y, np.concatenate([ref.mo[idx], ref.mi[idx]]))
        check_ref = _ring_check(fits, idx.size, DP)
        check = _ring_check_kernel(kernel._module, fits, idx.size, DP)
        np.testing.assert_array_equal(check[0], check_ref[0])  # the rings accepted
        for u, v in zip(check[1:], check_ref[1:], strict=True):  # centres, sigmas, residuals
            np.testing.assert_allclose(u, v, rtol=0, atol=PX_TOL)
    assert n_rings >= 12 * 14


def _locate_all(pairs: list[RenderedPair], on: bool) -> tuple[list[np.ndarray], list[np.ndarray], object]:
    previous = kernel.use_kernel(on)
    try:
        cal = scaled_rig(1920)
        tracker = MarkerTracker(cal, TrackingParams())
        full, tracked = [], []
        for k, p in enumerate(pairs):
            dl, dr = detect_rings_multi([(p.left, "left"), (p.right, "right")])
            full.append(match_and_triangulate(cal, dl, dr).points_mm)
            tracked.append(tracker.locate(p.left, p.right, k / 30.0).points_mm)
        return full, tracked, tracker.stats
    finally:
        kernel.use_kernel(previous)


def test_located_points_equal_the_numpy_code_on_the_bench_sequence(pairs: list[RenderedPair]) -> None:
    full_ref, tracked_ref, stats_ref = _locate_all(pairs, False)
    full, tracked, stats = _locate_all(pairs, True)
    assert stats == stats_ref
    for a, b in zip(full, full_ref, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8)
    for a, b in zip(tracked, tracked_ref, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def _ring_image(rng: np.random.Generator, cx: float, cy: float, a: float, ratio: float, ang: float,
                dark: bool, noise: float) -> np.ndarray:
    img = np.full((120, 140), 200 if dark else 40, dtype=np.uint8)
    ring = 40 if dark else 210
    centre = (round(cx * 16), round(cy * 16))
    cv2.ellipse(img, centre, (int(a * 16), int(a * ratio * 16)), math.degrees(ang), 0, 360, ring, -1,
                cv2.LINE_AA, 4)
    cv2.ellipse(img, centre, (int(a * 0.43 * 16), int(a * ratio * 0.43 * 16)), math.degrees(ang), 0, 360,
                int(img[0, 0]), -1, cv2.LINE_AA, 4)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    return np.clip(img + rng.normal(0.0, noise, img.shape), 0, 255).astype(np.uint8)


@pytest.mark.usefixtures("compiled")
@settings(max_examples=80, deadline=None)
@given(
    cx=st.floats(30, 110), cy=st.floats(30, 90), a=st.floats(3.0, 25.0), ratio=st.floats(0.45, 1.0),
    ang=st.floats(-1.5, 1.5), dark=st.booleans(), noise=st.floats(0.0, 12.0),
    n_rays=st.sampled_from([8, 16, 32]),
    dx=st.floats(-3, 3), dy=st.floats(-3, 3), scale=st.floats(0.7, 1.4), seed=st.integers(0, 10_000),
)
def test_random_rings_give_the_numpy_decisions_and_values(
    cx: float, cy: float, a: float, ratio: float, ang: float, dark: bool, noise: float, n_rays: int,
    dx: float, dy: float, scale: float, seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    img = _ring_image(rng, cx, cy, a, ratio, ang, dark, noise)
    # a second, unrelated seed on the same image (rays crossing the border, no ring)
    seeds = RingSeeds(
        np.array([[cx + dx, cy + dy], [rng.uniform(0, 140), rng.uniform(0, 120)]]),
        np.array([[a * scale, a * ratio * scale, ang], [rng.uniform(2, 30), rng.uniform(2, 20), 0.3]]),
        np.array([[0.43 * a * scale, 0.43 * a * ratio * scale, ang], [rng.uniform(0.8, 8), 1.0, 0.0]]),
        np.array([dark, not dark]),
    )
    ref = ring_edges_multi_numpy([(img, seeds)], n_rays, 25.0, 0.85)
    got = ring_edges_multi([(img, seeds)], n_rays, 25.0, 0.85)
    _assert_same_edges(got, ref)
    idx = np.nonzero(ref.ok)[0]  # the rings fit_rings fits
    _assert_same_fits(np.concatenate([ref.xo[idx], ref.xi[idx]]), np.concatenate([ref.yo[idx], ref.yi[idx]]),
                      np.concatenate([ref.mo[idx], ref.mi[idx]]))


@pytest.mark.usefixtures("compiled")
@settings(max_examples=150, deadline=None)
@given(
    cx=st.floats(-500, 2500), cy=st.floats(-500, 1500), a=st.floats(2.0, 80.0), ratio=st.floats(0.1, 1.0),
    ang=st.floats(-3.2, 3.2), noise=st.floats(0.0, 0.5), outliers=st.integers(0, 8), drop=st.integers(0, 30),
    R=st.sampled_from([12, 32, 48]), seed=st.integers(0, 10_000),
)
def test_random_point_sets_give_the_numpy_fits_and_inliers(
    cx: float, cy: float, a: float, ratio: float, ang: float, noise: float, outliers: int, drop: int,
    R: int, seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 2 * math.pi, (3, R))
    b = a * ratio
    X = cx + a * np.cos(t) * math.cos(ang) - b * np.sin(t) * math.sin(ang) + rng.normal(0, noise, (3, R))
    Y = cy + a * np.cos(t) * math.sin(ang) + b * np.sin(t) * math.cos(ang) + rng.normal(0, noise, (3, R))
    k = rng.integers(0, R, outliers)
    X[0, k] += rng.normal(0, 3.0, k.size)
    Y[0, k] += rng.normal(0, 3.0, k.size)
    M = np.ones((3, R), dtype=bool)
    M[1, rng.integers(0, R, drop)] = False
    X[2] = cx + rng.normal(0, 1.0, R)  # a degenerate set (no ellipse)
    _assert_same_fits(X, Y, M, max(PX_TOL, 200.0 * _rounding_sensitivity(X, Y, M)), rtol=1e-9)


def _rounding_sensitivity(X: np.ndarray, Y: np.ndarray, M: np.ndarray) -> float:
    """How far the numpy reference moves when only the order of the points changes (its sums'
    rounding): a tiny ellipse with a few noisy points, or points exactly on an ellipse (a singular
    reduced scatter matrix), is ill-conditioned and moves by more than 1e-9."""
    with np.errstate(all="ignore"):
        a, _ = fit_ellipse_arrays_numpy(X, Y, M)
        b, _ = fit_ellipse_arrays_numpy(X[:, ::-1], Y[:, ::-1], M[:, ::-1])
    g = a.good & b.good
    d = [np.abs(u[g] - v[g]).max(initial=0.0) for u, v in ((a.conic, b.conic), (a.center_px, b.center_px),
                                                         (a.a_px, b.a_px), (a.b_px, b.b_px))]
    return float(max(d))


# ---- bad input ------------------------------------------------------------------------------------
def _fit_args(E: int = 2, R: int = 8) -> list[np.ndarray]:
    return [np.zeros((E, R)), np.zeros((E, R)), np.ones((E, R), dtype=bool), np.empty((E, 3, 3)),
            np.empty((E, 2)), np.empty(E), np.empty(E), np.empty(E), np.empty(E),
            np.empty(E, dtype=np.int64), np.empty(E, dtype=bool), np.empty((E, R), dtype=bool)]


def _edge_args(E: int = 1, n: int = 4, S: int = 10) -> list[object]:
    f8, b1 = np.float64, np.bool_
    return [np.zeros((E, n, S), dtype=np.uint8), np.ones(E, dtype=b1), np.zeros((E, 2)), np.ones(n),
            np.zeros(n), np.full((E, n), 1.0), np.full((E, n), 0.5), np.full(E, S, dtype=np.int64), 25.0,
            0.85, np.empty((E, n), f8), np.empty((E, n), f8), np.empty((E, n), b1), np.empty((E, n), f8),
            np.empty((E, n), f8), np.empty((E, n), b1), np.empty(E, f8), np.empty(E, b1)]


@pytest.mark.parametrize(
    ("index", "value", "error", "message"),
    [
        (0, np.zeros((2, 8), dtype=np.float32), TypeError, "X: expected float64"),
        (0, [[0.0] * 8] * 2, TypeError, "X: expected an array"),
        (1, np.zeros((2, 7)), ValueError, "Y: dimension 1 is 7"),
        (2, np.ones((2, 8), dtype=np.uint8), TypeError, "M: expected bool"),
        (3, np.empty((2, 3, 3))[:, ::-1], ValueError, "conic: must be C-contiguous"),
        (4, np.empty((2, 3)), ValueError, "center: dimension 1 is 3"),
        (9, np.empty(2, dtype=np.int32), TypeError, "n_points: expected int64"),
        (11, np.empty((2, 8, 1), dtype=bool), ValueError, "used: expected 2 dimensions"),
    ],
)
def test_fit_ellipses_rejects_bad_buffers_naming_them(
    index: int, value: object, error: type, message: str
) -> None:
    k = kernel._module
    assert k is not None
    args: list[object] = list(_fit_args())
    args[index] = value
    with pytest.raises(error, match=message):
        k.fit_ellipses(*args)


def test_outputs_must_be_writable() -> None:
    k = kernel._module
    assert k is not None
    args: list[object] = list(_fit_args())
    out = np.empty(2)
    out.setflags(write=False)
    args[5] = out
    with pytest.raises(ValueError, match="a: must be writable"):
        k.fit_ellipses(*args)


@pytest.mark.parametrize(
    ("index", "value", "error", "message"),
    [
        (0, np.zeros((1, 4, 10), dtype=np.float32), TypeError, "grey: expected uint8"),
        (1, np.ones(2, dtype=bool), ValueError, "dark_on_light: dimension 0 is 2"),
        (3, np.ones(5), ValueError, "cos_t: dimension 0 is 5"),
        (7, np.full(1, 11, dtype=np.int64), ValueError, "n_samples: ring 0 has 11"),
        (7, np.full(1, 0, dtype=np.int64), ValueError, "n_samples: ring 0 has 0"),
        (12, np.empty((1, 4)), TypeError, "mo: expected bool"),
        (17, np.empty(1), TypeError, "ok: expected bool"),
    ],
)
def test_ring_edges_rejects_bad_buffers_naming_them(
    index: int, value: object, error: type, message: str
) -> None:
    k = kernel._module
    assert k is not None
    args = _edge_args()
    args[index] = value
    with pytest.raises(error, match=message):
        k.ring_edges(*args)


def test_ring_geometry_rejects_non_finite_and_huge_radii() -> None:
    k = kernel._module
    assert k is not None
    theta = np.linspace(0, 6, 8)
    out = [np.empty((1, 8)), np.empty((1, 8)), np.empty(1, dtype=np.int64)]
    with pytest.raises(ValueError, match="not finite"):
        k.ring_geometry(np.array([[np.nan, 1.0, 0.0]]), np.array([[1.0, 1.0, 0.0]]), theta, *out)
    with pytest.raises(ValueError, match="samples per ray"):
        k.ring_geometry(np.array([[1e9, 1e9, 0.0]]), np.array([[1.0, 1.0, 0.0]]), theta, *out)
    with pytest.raises(ValueError, match="inner: dimension 0"):
        k.ring_geometry(np.zeros((1, 3)), np.zeros((2, 3)), theta, *out)
    with pytest.raises(ValueError, match="mapx: dimension 1"):
        k.ray_maps(np.zeros((1, 2)), np.ones(8), np.ones(8), np.empty((1, 7, 4), np.float32),
                   np.empty((1, 7, 4), np.float32))


def test_normal_correction_rejects_bad_buffers_naming_them() -> None:
    k = kernel._module
    assert k is not None
    P = 2
    args: list[object] = [np.zeros((4 * P, 3, 3)), np.ones((2 * P, 2)), np.eye(3), np.eye(3), np.eye(3),
                          np.zeros((P, 2)), np.zeros((P, 2)), np.empty((P, 3)), np.empty(P, dtype=bool)]
    bad = list(args)
    bad[0] = np.zeros((4 * P + 1, 3, 3))
    with pytest.raises(ValueError, match="C: dimension 0 is 9"):
        k.normal_correction(*bad)
    bad = list(args)
    bad[6] = np.zeros((P, 2), dtype=np.float32)
    with pytest.raises(TypeError, match="UR: expected float64"):
        k.normal_correction(*bad)
    bad = list(args)
    bad[2] = np.eye(3)[:, ::-1]
    with pytest.raises(ValueError, match="K_left: must be C-contiguous"):
        k.normal_correction(*bad)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), depth=st.floats(300.0, 3000.0), spread=st.floats(1.0, 400.0),
       n=st.integers(1, 40))
def test_dlt_triangulation_equals_the_numpy_svd(seed: int, depth: float, spread: float, n: int) -> None:
    k = kernel._module
    assert k is not None
    const = scaled_rig(1920).constants
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-spread, spread, (n, 2)), depth + rng.uniform(-spread, spread, n)])
    uv = []
    for P in (const.P_left, const.P_right):
        h = np.column_stack([X, np.ones(n)]) @ P.T
        uv.append(h[:, :2] / h[:, 2:] + rng.normal(0.0, 0.05, (n, 2)))
    ref = triangulate_dlt(const.P_left, const.P_right, uv[0], uv[1])
    pts, ok = np.empty((n, 3)), np.empty(n, dtype=bool)
    k.triangulate_dlt(np.ascontiguousarray(const.P_left), np.ascontiguousarray(const.P_right), uv[0], uv[1],
                      pts, ok)
    assert ok.all()
    # both are accurate to rounding times the depth's conditioning (baseline 120 mm)
    np.testing.assert_allclose(pts, ref, rtol=0, atol=1e-11 * depth * max(depth / 120.0, 1.0))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), depth=st.floats(300.0, 3000.0), n=st.integers(1, 30))
def test_ray_gaps_equal_the_numpy_midpoint_gaps(seed: int, depth: float, n: int) -> None:
    cal = scaled_rig(1920)
    const, R = cal.constants, cal.R_right_from_left
    rng = np.random.default_rng(seed)
    UL = rng.uniform(0, 1920, (n, 2))
    UR = UL - np.array([1394.0 * 120.0 / depth, 0.0]) + rng.normal(0.0, 2.0, (n, 2))
    ref = stereo._ray_gaps(cal, UL, UR)  # the kernel when built
    previous = kernel.use_kernel(False)
    try:
        want = stereo._ray_gaps(cal, UL, UR)
    finally:
        kernel.use_kernel(previous)
    assert kernel._module is not None
    np.testing.assert_allclose(ref, want, rtol=1e-9, atol=1e-12)
    gaps, ok = np.empty(n), np.empty(n, dtype=bool)
    mats = [np.ascontiguousarray(a) for a in (const.K_left_inv, const.K_right_inv, R, const.right_center_mm)]
    kernel._module.ray_gaps(UL, UR, *mats, gaps, ok)
    assert ok.all()
    np.testing.assert_allclose(gaps, want, rtol=1e-9, atol=1e-12)


def _selected(on: bool, fn: Any, *args: Any) -> Any:
    """``fn(*args)`` with the compiled kernel (``on``) or the numpy code selected (the previous
    selection restored after)."""
    assert kernel._module is not None, kernel.kernel_status()
    previous = kernel.use_kernel(on)
    try:
        return fn(*args)
    finally:
        kernel.use_kernel(previous)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 40),
       k1=st.floats(0.001, 0.4) | st.floats(-0.4, -0.001), k2=st.floats(-0.2, 0.2),
       p=st.floats(-0.01, 0.01), k3=st.floats(-0.05, 0.05), side=st.sampled_from(["left", "right"]))
def test_ideal_pixels_and_affine_maps_equal_the_numpy_code(
    seed: int, n: int, k1: float, k2: float, p: float, k3: float, side: str
) -> None:
    """The compiled undistortion is OpenCV's fixed point (same criteria): the ideal centres and the
    affine maps within 1e-9 px over the image and beyond, for lens-like distortion."""
    cal = StereoCalibration.synthetic(f_px=1394.0, image_size=(1920, 1080), dist=[k1, k2, p, -p, k3])
    rng = np.random.default_rng(seed)
    centers = rng.uniform([-50.0, -50.0], [1970.0, 1130.0], (n, 2))
    ideal, H = _selected(True, stereo._ideal_with_affines, cal, side, centers)
    want, H_want = _selected(False, stereo._ideal_with_affines, cal, side, centers)
    assert H is not None
    assert H_want is not None
    np.testing.assert_allclose(ideal, want, rtol=0, atol=PX_TOL)
    np.testing.assert_allclose(H, H_want, rtol=0, atol=PX_TOL)
    assert np.array_equal(H[:, 2], np.tile([0.0, 0.0, 1.0], (n, 1)))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), m=st.integers(1, 40))
def test_conics_through_affine_maps_equal_the_numpy_code(seed: int, m: int) -> None:
    rng = np.random.default_rng(seed)
    C = rng.normal(size=(m, 3, 3))
    C = C + np.transpose(C, (0, 2, 1))
    H = np.zeros((m, 3, 3))
    H[:, :2, :2] = np.eye(2) + rng.normal(0.0, 0.05, (m, 2, 2))
    H[:, :2, 2] = rng.normal(0.0, 5.0, (m, 2))
    H[:, 2, 2] = 1.0
    got = _selected(True, stereo._to_ideal_stack, C, H)
    want = _selected(False, stereo._to_ideal_stack, C, H)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.sum(got * got, axis=(1, 2)), 1.0, rtol=1e-12)


def test_an_undistortion_that_does_not_converge_is_flagged_and_left_to_opencv() -> None:
    """Strong barrel distortion at the image corner: the fixed point runs away (OpenCV versions
    stop it differently), so the kernel flags the point and the stereo stage takes OpenCV's."""
    k = kernel._module
    assert k is not None
    cal = StereoCalibration.synthetic(f_px=1394.0, image_size=(1920, 1080), dist=[-0.25, 0.0, 0.0, 0.0, 0.0])
    centers = np.array([[960.0, 540.0], [32.77, -30.5]])
    ideal, H, ok = np.empty((2, 2)), np.empty((2, 3, 3)), np.empty(2, dtype=bool)
    K, dist = np.ascontiguousarray(cal.K_left), np.ascontiguousarray(cal.dist_left)
    k.ideal_affines(centers, K, dist, ideal, H, ok)
    assert ok.tolist() == [True, False]
    got, H_got = _selected(True, stereo._ideal_with_affines, cal, "left", centers)
    want, H_want = _selected(False, stereo._ideal_with_affines, cal, "left", centers)
    assert np.array_equal(got, want)
    assert np.array_equal(H_got, H_want)


def test_ideal_affines_and_conics_reject_bad_buffers_naming_them() -> None:
    k = kernel._module
    assert k is not None
    with pytest.raises(ValueError, match="dist: dimension 0 is 4, expected 5"):
        k.ideal_affines(np.zeros((2, 2)), np.eye(3), np.zeros(4), np.empty((2, 2)), np.empty((2, 3, 3)),
                        np.empty(2, dtype=bool))
    with pytest.raises(ValueError, match="H: dimension 0 is 3, expected 2"):
        k.ideal_affines(np.zeros((2, 2)), np.eye(3), np.zeros(5), np.empty((2, 2)), np.empty((3, 3, 3)),
                        np.empty(2, dtype=bool))
    with pytest.raises(TypeError, match="centers: expected float64"):
        k.ideal_affines(np.zeros((2, 2), np.float32), np.eye(3), np.zeros(5), np.empty((2, 2)),
                        np.empty((2, 3, 3)), np.empty(2, dtype=bool))
    ro = np.empty((2, 3, 3))
    ro.flags.writeable = False
    with pytest.raises(ValueError, match="out: must be writable"):
        k.conics_to_ideal(np.zeros((2, 3, 3)), np.tile(np.eye(3), (2, 1, 1)), ro)
    with pytest.raises(ValueError, match="H: dimension 0 is 1, expected 2"):
        k.conics_to_ideal(np.zeros((2, 3, 3)), np.zeros((1, 3, 3)), np.empty((2, 3, 3)))


def _detection(C_outer: np.ndarray, C_inner: np.ndarray) -> RingDetection:
    outer, inner = ellipse_from_conic(C_outer), ellipse_from_conic(C_inner)
    assert outer is not None
    assert inner is not None
    return RingDetection(outer.center_px, 0.01, outer, inner, 0.05, True, 1.0)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 12), tilt=st.floats(0.0, 1.2),
       noise=st.floats(0.0, 0.05))
def test_plane_normal_correction_equals_the_numpy_code(seed: int, n: int, tilt: float, noise: float) -> None:
    cal = scaled_rig(1920)
    R, t = cal.R_right_from_left, cal.t_right_from_left_mm.reshape(3)
    rng = np.random.default_rng(seed)
    left, right = [], []
    for _ in range(n):
        c = np.array([rng.uniform(-200, 200), rng.uniform(-120, 120), rng.uniform(500, 1500)])
        az = rng.uniform(0, 2 * math.pi)
        normal = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), -math.cos(tilt)])
        cones = []
        for K, cc, nn in ((cal.K_left, c, normal), (cal.K_right, R @ c + t, R @ normal)):
            nn = nn + rng.normal(0.0, noise, 3)  # each view its own (measurement-like) error
            cc = cc + rng.normal(0.0, 5.0 * noise, 3)
            cones.append(_detection(*(circle_image_conic(K, cc, nn / np.linalg.norm(nn), radius)
                                      for radius in (3.5, 1.5))))
        left.append(cones[0])
        right.append(cones[1])
    UL0 = np.array([d.center_px for d in left])
    UR0 = np.array([d.center_px for d in right])
    out = {}
    for on in (False, True):
        previous = kernel.use_kernel(on)
        try:
            UL, UR = UL0.copy(), UR0.copy()
            normals = stereo._normal_correction(cal, left, right, None, None, UL, UR)
        finally:
            kernel.use_kernel(previous)
        out[on] = (UL, UR, normals)
    (UL_n, UR_n, N_n), (UL_k, UR_k, N_k) = out[False], out[True]
    assert [v is None for v in N_k] == [v is None for v in N_n]  # the same pairs corrected
    np.testing.assert_allclose(UL_k, UL_n, rtol=0, atol=1e-9)
    np.testing.assert_allclose(UR_k, UR_n, rtol=0, atol=1e-9)
    for a, b in zip(N_k, N_n, strict=True):
        if a is not None and b is not None:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def test_many_calls_leak_neither_memory_nor_references(pairs: list[RenderedPair]) -> None:
    k = kernel._module
    assert k is not None
    p = pairs[0]
    parts = [(begin_search(p.left, DP).frame, begin_search(p.left, DP).seeds)]
    ref = ring_edges_multi_numpy(parts, DP.n_rays, DP.min_contrast, DP.min_valid_fraction)
    fit_args = _fit_args(ref.xo.shape[0], DP.n_rays)
    fit_args[0], fit_args[1], fit_args[2] = ref.xo, ref.yo, ref.mo
    bad = list(fit_args)
    bad[4] = np.empty((1, 2))
    counts = [sys.getrefcount(a) for a in fit_args]
    previous = kernel.use_kernel(True)
    try:
        for _ in range(50):
            ring_edges_multi(parts, DP.n_rays, DP.min_contrast, DP.min_valid_fraction)
        gc.collect()
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(2000):
            ring_edges_multi(parts, DP.n_rays, DP.min_contrast, DP.min_valid_fraction)
            k.fit_ellipses(*fit_args)
            with pytest.raises(ValueError):
                k.fit_ellipses(*bad)
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.stop()
    finally:
        kernel.use_kernel(previous)
    assert grown < 64 * 1024
    assert [sys.getrefcount(a) for a in fit_args] == counts
