"""The batched forms (issue 17 speed-up) against the one-at-a-time forms they replace."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.vision.camera_model import StereoCalibration
from hil.vision.conics import circle_image_conic, conic_center, conic_centers
from hil.vision.detect import DetectParams, detect_rings, detect_rings_multi, edges_of, fit_rings
from hil.vision.ellipse import (
    _direct_fit_batch,
    circle_normals_from_conic,
    circle_normals_from_conics,
    fit_conic_direct,
    fit_ellipse_arrays,
    projected_center_from_normal,
    projected_centers_from_normals,
)
from hil.vision.render import RenderedPair, RingMarker3D
from hil.vision.ring_edges import RingSeeds, ring_edges_multi

K = np.array([[1394.0, 0.0, 959.5], [0.0, 1394.0, 539.5], [0.0, 0.0, 1.0]])


def _points(cx: float, cy: float, a: float, b: float, ang: float, noise: float, seed: int) -> np.ndarray:
    t = np.linspace(0, 2 * math.pi, 32, endpoint=False)
    x = cx + a * np.cos(t) * math.cos(ang) - b * np.sin(t) * math.sin(ang)
    y = cy + a * np.cos(t) * math.sin(ang) + b * np.sin(t) * math.cos(ang)
    rng = np.random.default_rng(seed)
    return np.stack([x, y]) + rng.normal(0.0, noise, (2, 32))


def _same_conic(C1: np.ndarray, C2: np.ndarray) -> float:
    C1 = C1 / np.linalg.norm(C1) * np.sign(C1[0, 0])
    C2 = C2 / np.linalg.norm(C2) * np.sign(C2[0, 0])
    return float(np.abs(C1 - C2).max())


@settings(max_examples=60, deadline=None)
@given(
    cx=st.floats(0, 1900), cy=st.floats(0, 1000), a=st.floats(3.0, 60.0), ratio=st.floats(0.3, 1.0),
    ang=st.floats(-1.5, 1.5), noise=st.floats(0.01, 0.3), seed=st.integers(0, 1000),
)
def test_batch_direct_fit_equals_the_single_fit(
    cx: float, cy: float, a: float, ratio: float, ang: float, noise: float, seed: int
) -> None:
    p = _points(cx, cy, a, a * ratio, ang, noise * a / 10, seed)
    single = fit_conic_direct(p[0], p[1])
    assert single is not None
    C, ok = _direct_fit_batch(p[0][None, :], p[1][None, :], np.ones((1, 32)))
    assert ok[0]
    assert _same_conic(C[0], single) < 1e-8


def test_a_degenerate_set_in_a_batch_is_flagged_and_spares_the_others() -> None:
    good = _points(100.0, 80.0, 10.0, 6.0, 0.3, 0.05, 1)
    line = np.stack([np.linspace(0, 10, 32), np.linspace(0, 5, 32)])  # collinear: no ellipse
    X, Y = np.stack([good[0], line[0], good[0]]), np.stack([good[1], line[1], good[1]])
    f = fit_ellipse_arrays(X, Y, np.ones((3, 32), dtype=bool))
    assert f.good.tolist() == [True, False, True]
    np.testing.assert_allclose(f.center_px[0], f.center_px[2])
    np.testing.assert_allclose(f.center_px[0], [100.0, 80.0], atol=0.05)


def test_batch_normals_and_projected_centres_equal_the_single_ones() -> None:
    rng = np.random.default_rng(3)
    conics, normals_true = [], []
    for _ in range(6):
        c = np.array([rng.uniform(-100, 100), rng.uniform(-80, 80), rng.uniform(400, 1200)])
        n = rng.normal(size=3)
        n[2] = -abs(n[2]) - 0.5
        n /= np.linalg.norm(n)
        conics.append(circle_image_conic(K, c, n, 3.5))
        normals_true.append(n)
    C = np.stack(conics)
    n1, n2, ok = circle_normals_from_conics(C, K)
    assert ok.all()
    for k in range(6):
        single = circle_normals_from_conic(C[k], K)
        assert single is not None
        got = {tuple(np.round(n1[k], 9)), tuple(np.round(n2[k], 9))}
        assert got == {tuple(np.round(single[0], 9)), tuple(np.round(single[1], 9))}
    N = np.stack(normals_true)
    batch = projected_centers_from_normals(C, K, N)
    for k in range(6):
        np.testing.assert_allclose(batch[k], projected_center_from_normal(C[k], K, N[k]), atol=1e-9)
        np.testing.assert_allclose(conic_centers(C)[k], conic_center(C[k]), atol=1e-9)


def test_two_images_in_one_batch_equal_one_at_a_time(
    cal: StereoCalibration, scene: tuple[list[RingMarker3D], RenderedPair]
) -> None:
    _, pair = scene
    params = DetectParams()
    both = detect_rings_multi([(pair.left, "left"), (pair.right, "right")], params)
    for got, img in zip(both, (pair.left, pair.right), strict=True):
        alone = detect_rings(img, params)
        assert len(got) == len(alone) == 8
        for a, b in zip(got, alone, strict=True):
            np.testing.assert_allclose(a.center_px, b.center_px, atol=1e-9)
    # ray edges seeded from the detections, both images at once vs each alone
    seeds = [
        RingSeeds(
            np.array([d.center_px for d in dets]),
            np.array([[d.outer.a_px, d.outer.b_px, d.outer.angle_rad] for d in dets]),
            np.array([[d.inner.a_px, d.inner.b_px, d.inner.angle_rad] for d in dets]),
            np.array([d.dark_on_light for d in dets]),
        )
        for dets in both
    ]
    joint = ring_edges_multi(
        [(pair.left, seeds[0]), (pair.right, seeds[1])], params.n_rays, params.min_contrast,
        params.min_valid_fraction,
    )
    left_alone, right_alone = edges_of(pair.left, seeds[0], params), edges_of(pair.right, seeds[1], params)
    np.testing.assert_array_equal(joint.xo[:8][joint.mo[:8]], left_alone.xo[left_alone.mo])
    np.testing.assert_array_equal(joint.yi[8:][joint.mi[8:]], right_alone.yi[right_alone.mi])
    # re-fitting from a detection's own centre reproduces it (the tracking step's fixed point)
    refit = fit_rings(left_alone, params)
    for d, r in zip(both[0], refit, strict=True):
        assert r is not None
        assert float(np.linalg.norm(d.center_px - r.center_px)) < 0.05
