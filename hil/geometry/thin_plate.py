"""Thin-plate spline interpolation over the skin's (x, y) (Bookstein 1989, IEEE TPAMI 11(6)).

Used where recorded skin points drive the simulated deformable body, and by the local change
estimator of COMPENSATE (:mod:`hil.controller.change_estimate`): the
spline through the recorded displacements is exact at the recorded points, minimises bending
energy between them and is affine far from them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def thin_plate_weights(places_xy: FloatArray, query_xy: FloatArray) -> FloatArray:
    """Thin-plate spline interpolation (Bookstein 1989, kernel ``r^2 log r``) as a matrix: the
    values at ``query_xy`` (M, 2) are ``W @ values at places_xy`` (n, 2), W (M, n).

    Raises:
        ValueError: fewer than 3 places, collinear ones (the affine part is not determined) or two
            at the same place.
    """
    n = len(places_xy)
    if n < 3:
        raise ValueError(f"{n} recorded skin point(s): the thin-plate spline needs at least 3")
    P = np.column_stack([np.ones(n), places_xy])
    sv = np.linalg.svd(places_xy - places_xy.mean(axis=0), compute_uv=False)
    if not sv[1] > 1e-6 * max(float(sv[0]), 1.0):
        raise ValueError("the recorded skin points' places are collinear: the spline needs 3 not on a line")
    gaps = np.linalg.norm(places_xy[:, None, :] - places_xy[None, :, :], axis=2) + np.eye(n)
    if not gaps.min() > 1e-6:
        raise ValueError("two recorded skin points have the same place on the skin")

    def U(a: FloatArray, b: FloatArray) -> FloatArray:
        r2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            out: FloatArray = np.where(r2 > 0.0, 0.5 * r2 * np.log(np.where(r2 > 0.0, r2, 1.0)), 0.0)
        return out

    L = np.zeros((n + 3, n + 3))
    L[:n, :n] = U(places_xy, places_xy)
    L[:n, n:] = P
    L[n:, :n] = P.T
    Q = np.hstack([U(query_xy, places_xy), np.column_stack([np.ones(len(query_xy)), query_xy])])
    W: FloatArray = Q @ np.linalg.solve(L, np.eye(n + 3)[:, :n])
    return W
