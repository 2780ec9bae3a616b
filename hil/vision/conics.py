"""Conic helpers: the image of a 3D circle, conic centres, and the projected centre of two
concentric circles (the perspective-bias correction for ring markers).

A conic is a symmetric 3x3 matrix ``C`` with ``x^T C x = 0`` for homogeneous points on it; the
coefficients ``(a, b, c, d, e, f)`` of seed 001 eq 12 map to
``C = [[a, b/2, d/2], [b/2, c, e/2], [d/2, e/2, f]]``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def conic_from_coeffs(coeffs: FloatArray) -> FloatArray:
    a, b, c, d, e, f = (float(v) for v in coeffs)
    return np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])


def conic_center(C: FloatArray) -> FloatArray:
    """Centre of an ellipse conic (seed 001 eq 17): the 2x2 gradient system solved in closed form,
    ``x_c = (b e - 2 c d) / (4 a c - b^2)``, ``y_c = (b d - 2 a e) / (4 a c - b^2)``.

    Raises:
        np.linalg.LinAlgError: the conic has no centre (a parabola).
    """
    a, b, c = float(C[0, 0]), float(C[0, 1]), float(C[1, 1])
    d, e = float(C[0, 2]), float(C[1, 2])
    det = a * c - b * b
    if det == 0.0:
        raise np.linalg.LinAlgError("conic has no centre")
    return np.array([(b * e - c * d) / det, (b * d - a * e) / det])


def plane_basis(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors spanning the plane orthogonal to ``normal``."""
    n0, n1, n2 = (float(v) for v in normal)
    s = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    n0, n1, n2 = n0 / s, n1 / s, n2 / s
    if abs(n0) < 0.9:  # e1 = n x (1, 0, 0)
        a0, a1, a2 = 0.0, n2, -n1
    else:  # e1 = n x (0, 1, 0)
        a0, a1, a2 = -n2, 0.0, n0
    s = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    a0, a1, a2 = a0 / s, a1 / s, a2 / s
    e2 = (n1 * a2 - n2 * a1, n2 * a0 - n0 * a2, n0 * a1 - n1 * a0)
    return np.array([a0, a1, a2]), np.array(e2)


def circle_image_conic(
    K: FloatArray, center_cam_mm: FloatArray, normal_cam: FloatArray, radius_mm: float
) -> FloatArray:
    """Pixel conic of a circle (centre, normal, radius in the camera frame) seen by an ideal
    (undistorted) pinhole camera ``K``: ``C = H^-T diag(1, 1, -r^2) H^-1`` with ``H = K [e1 e2 c]``."""
    e1, e2 = plane_basis(normal_cam)
    H = K @ np.column_stack([e1, e2, center_cam_mm])
    Hi = np.linalg.inv(H)
    C = Hi.T @ np.diag([1.0, 1.0, -(radius_mm**2)]) @ Hi
    return np.asarray(C / np.linalg.norm(C), dtype=np.float64)


def concentric_center(C_outer: FloatArray, C_inner: FloatArray) -> FloatArray | None:
    """Image of the common centre of two concentric circles from their image conics.

    For concentric circles ``C_i = diag(1, 1, -r_i^2)`` in the plane, ``C_o^-1 C_i`` has one simple
    eigenvalue whose eigenvector is the centre (0, 0, 1); a homography conjugates the product, so
    the simple eigenvector of the image conics' product is the image of the centre (pole-polar
    relation: the centre is the pole of the vanishing line with respect to both conics).
    Returns (2,) pixels or None when the eigen-structure is not the expected one.
    """
    try:
        M = np.linalg.solve(C_outer, C_inner)
    except np.linalg.LinAlgError:
        return None
    w, V = np.linalg.eig(M)
    if np.max(np.abs(w.imag)) > 1e-6 * np.max(np.abs(w)):
        # complex pair: the two near-equal eigenvalues split into a conjugate pair; the simple
        # eigenvalue is the real one.
        k = int(np.argmin(np.abs(w.imag)))
    else:
        wr = w.real
        d = [abs(wr[i] - np.mean(np.delete(wr, i))) for i in range(3)]
        k = int(np.argmax(d))
    v = V[:, k].real
    if abs(v[2]) < 1e-12:
        return None
    return np.asarray(v[:2] / v[2], dtype=np.float64)


def conic_centers(C: FloatArray) -> FloatArray:
    """:func:`conic_center` of a stack of ellipse conics (P, 3, 3) -> (P, 2) (NaN for a parabola)."""
    a, b, c = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    d, e = C[:, 0, 2], C[:, 1, 2]
    det = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([(b * e - c * d) / det, (b * d - a * e) / det], axis=1)
