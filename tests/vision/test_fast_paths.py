"""The closed forms and OpenCV work-arounds of the vision speed-up against the library calls they
replace: same numbers (to rounding) or the same pixels."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hil.vision.camera_model import StereoCalibration
from hil.vision.detect import _median3
from hil.vision.ellipse import _sampson_batch, sampson_distances
from hil.vision.sym3 import adj_sym3, det_sym3, ellipse_eigvec

_C1 = np.array([[0.0, 0.0, 2.0], [0.0, -1.0, 0.0], [2.0, 0.0, 0.0]])


def _spd(seed: int, count: int, cond: float) -> np.ndarray:
    """Random symmetric positive definite 3x3 matrices with condition numbers up to ``cond``."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    lam = np.exp(rng.uniform(0.0, np.log(cond), size=(count, 3)))
    return np.asarray(Q @ (lam[:, :, None] * np.transpose(Q, (0, 2, 1))), dtype=np.float64)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), cond=st.floats(1.0, 1e6))
def test_det_and_adjugate_equal_numpy(seed: int, cond: float) -> None:
    S = _spd(seed, 16, cond)
    scale = np.linalg.norm(S, axis=(1, 2)) ** 3  # the cancellation error of a 3x3 determinant
    assert np.all(np.abs(det_sym3(S) - np.linalg.det(S)) <= 1e-13 * scale)
    residual = S @ adj_sym3(S) - det_sym3(S)[:, None, None] * np.eye(3)  # S adj(S) = det(S) I
    assert np.all(np.abs(residual) <= 1e-13 * scale[:, None, None])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), cond=st.floats(1.0, 1e6))
def test_ellipse_eigvec_is_the_positive_generalised_eigenvector(seed: int, cond: float) -> None:
    S = _spd(seed, 16, cond)
    a, lam, ok = ellipse_eigvec(S)
    assert ok.all()
    for k in range(16):
        # reference: the eigenvalues of C1^-1 S are 1 / the pencil's; exactly one is positive
        w, V = np.linalg.eig(np.linalg.solve(_C1, S[k]))
        w, V = w.real, V.real
        pos = np.nonzero(w > 0)[0]
        assert pos.size == 1
        ref = V[:, pos[0]]
        np.testing.assert_allclose(lam[k], w[pos[0]], rtol=1e-7)
        cos = abs(float(a[k] @ ref)) / (np.linalg.norm(a[k]) * np.linalg.norm(ref))
        assert cos > 1.0 - 1e-10
        assert 4.0 * a[k, 0] * a[k, 2] - a[k, 1] ** 2 > 0


def test_ellipse_eigvec_flags_a_matrix_that_is_not_positive_definite() -> None:
    S = np.stack([np.eye(3), np.diag([1.0, -1.0, 1.0]), np.zeros((3, 3))])
    _, _, ok = ellipse_eigvec(S)
    assert ok.tolist() == [True, False, False]


def test_batched_sampson_distances_equal_the_single_ones() -> None:
    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    X = 300.0 + 9.0 * np.cos(t)[None, :] + rng.normal(0.0, 0.2, (4, 24))
    Y = 200.0 + 5.0 * np.sin(t)[None, :] + rng.normal(0.0, 0.2, (4, 24))
    C = np.stack([
        np.array([[1 / 81, 0.0, -300 / 81], [0.0, 1 / 25, -200 / 25],
                  [-300 / 81, -200 / 25, 300**2 / 81 + 200**2 / 25 - 1.0]]) * s
        for s in (1.0, -2.0, 0.5, 3.0)
    ])
    batch = _sampson_batch(C, X, Y)
    for k in range(4):
        np.testing.assert_allclose(batch[k], sampson_distances(C[k], X[k], Y[k]), rtol=1e-9, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(img=arrays(np.uint8, st.tuples(st.integers(1, 40), st.integers(1, 100))), view=st.booleans())
def test_median3_equals_opencv_pixel_for_pixel(img: np.ndarray, view: bool) -> None:
    if view and img.shape[1] > 2:  # a ROI view of a larger image, as the detector passes
        img = img[:, 1:-1]
    np.testing.assert_array_equal(_median3(img), cv2.medianBlur(np.ascontiguousarray(img), 3))


def test_rig_constants_are_the_calibrations_own_matrices() -> None:
    cal = StereoCalibration.synthetic(dist=[-0.05, 0.02, 0.0, 0.0, 0.0])
    c = cal.constants
    assert c is cal.constants  # computed once
    np.testing.assert_array_equal(c.P_left, cal.P_left())
    np.testing.assert_array_equal(c.P_right, cal.P_right())
    np.testing.assert_array_equal(c.K_left_inv, np.linalg.inv(cal.K_left))
    np.testing.assert_array_equal(c.right_center_mm, cal.right_center_mm)
    assert c.distorted_left
    assert c.distorted_right
    assert not c.P_left.flags.writeable
    assert not StereoCalibration.synthetic().constants.distorted_left
