"""Ellipse fitting: the paper's least squares (seed 001 eqs 12-17) and the direct ellipse-specific
fit (Fitzgibbon, Pilu & Fisher 1999, in the numerically stable form of Halir & Flusser 1998),
plus conic -> ellipse parameters, Sampson residuals, and the supporting-plane normals of a circle
seen as an ellipse (for the perspective-bias correction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.vision import kernel
from hil.vision.frozen import frozen_instance
from hil.vision.sym3 import adj_sym3, det_sym3, ellipse_eigvec

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Ellipse:
    """An ellipse in pixels: centre, semi-axes ``a >= b``, angle of the major axis (rad, from +x),
    the normalised conic matrix, the RMS Sampson residual of the fitted points and their count."""

    center_px: FloatArray
    a_px: float
    b_px: float
    angle_rad: float
    conic: FloatArray
    residual_rms_px: float
    n_points: int

    def to_dict(self) -> dict[str, object]:
        return {
            "center_px": [float(v) for v in self.center_px],
            "a_px": self.a_px,
            "b_px": self.b_px,
            "angle_rad": self.angle_rad,
            "residual_rms_px": self.residual_rms_px,
            "n_points": self.n_points,
        }


def _normalisation(x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    mx, my = float(x.mean()), float(y.mean())
    xc, yc = x - mx, y - my
    s = math.sqrt(float(xc @ xc + yc @ yc) / (2.0 * x.size)) or 1.0
    N = np.array([[1 / s, 0.0, -mx / s], [0.0, 1 / s, -my / s], [0.0, 0.0, 1.0]])
    return xc / s, yc / s, N


def _coeffs_to_conic(v: FloatArray) -> FloatArray:
    a, b, c, d, e, f = v
    return np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])


def fit_conic_direct(x: FloatArray, y: FloatArray) -> FloatArray | None:
    """Direct least-squares ellipse-specific fit (Fitzgibbon 1999 / Halir-Flusser 1998).

    Minimises the algebraic distance subject to ``4ac - b^2 = 1``, which always returns an ellipse.
    Returns the 3x3 conic (pixels) or None when fewer than 5 points or the system is degenerate.
    """
    if x.size < 5:
        return None
    xn, yn, N = _normalisation(x, y)
    D = np.empty((6, xn.size))
    D[0], D[1], D[2], D[3], D[4], D[5] = xn * xn, xn * yn, yn * yn, xn, yn, 1.0
    S = D @ D.T
    S1, S2, S3 = S[:3, :3], S[:3, 3:], S[3:, 3:]
    try:
        T = -np.linalg.inv(S3) @ S2.T
    except np.linalg.LinAlgError:
        return None
    M = S1 + S2 @ T
    M = np.stack([M[2] / 2.0, -M[1], M[0] / 2.0])
    _, V = np.linalg.eig(M)
    V = V.real
    cond = 4.0 * V[0] * V[2] - V[1] ** 2
    ok = np.nonzero(cond > 0)[0]
    if ok.size == 0:
        return None
    a1 = V[:, ok[0]]
    Cn = _coeffs_to_conic(np.concatenate([a1, T @ a1]))
    C = N.T @ Cn @ N
    return np.asarray(C / np.linalg.norm(C), dtype=np.float64)


def fit_conic_paper(x: FloatArray, y: FloatArray) -> FloatArray | None:
    """Seed 001 eqs 13-16: ordinary least squares of the general conic.

    As printed, eq 14 keeps a constant column *and* a right-hand side of ones, which has the
    trivial solution (0, ..., 0, 1); the usable form drops the constant (``f = -1``):
    ``[x^2 xy y^2 x y] X = 1``, ``X = (A^T A)^-1 A^T 1`` (eq 16). Coordinates are taken relative to
    the points' mean (the paper's ROI-corner offset) for conditioning. Not ellipse-specific: noisy
    points can return a hyperbola (then None).
    """
    if x.size < 5:
        return None
    mx, my = float(x.mean()), float(y.mean())
    xs, ys = x - mx, y - my
    A = np.stack([xs * xs, xs * ys, ys * ys, xs, ys], axis=1)
    sol, *_ = np.linalg.lstsq(A, np.ones_like(xs), rcond=None)
    a, b, c, d, e = sol
    if 4 * a * c - b * b <= 0:
        return None
    Cl = _coeffs_to_conic(np.array([a, b, c, d, e, -1.0]))
    Tm = np.array([[1.0, 0.0, -mx], [0.0, 1.0, -my], [0.0, 0.0, 1.0]])
    C = Tm.T @ Cl @ Tm
    return np.asarray(C / np.linalg.norm(C), dtype=np.float64)


def sampson_distances(C: FloatArray, x: FloatArray, y: FloatArray) -> FloatArray:
    """First-order geometric distance of points to the conic (pixels)."""
    gx = C[0, 0] * x + C[0, 1] * y + C[0, 2]
    gy = C[1, 0] * x + C[1, 1] * y + C[1, 2]
    alg = gx * x + gy * y + (C[2, 0] * x + C[2, 1] * y + C[2, 2])
    grad = 2.0 * np.sqrt(gx * gx + gy * gy)
    return np.asarray(alg / np.maximum(grad, 1e-300), dtype=np.float64)


def ellipse_from_conic(
    C: FloatArray,
    x: FloatArray | None = None,
    y: FloatArray | None = None,
    residuals: FloatArray | None = None,
) -> Ellipse | None:
    """Ellipse parameters of a conic (None if it is not a real ellipse). With points, also the
    RMS Sampson residual."""
    if C[0, 0] + C[1, 1] < 0:
        C = -C
    A, B, Cq = float(C[0, 0]), float(C[0, 1]), float(C[1, 1])
    det = A * Cq - B * B
    if det <= 0:
        return None
    d, e = float(C[0, 2]), float(C[1, 2])
    cx, cy = (B * e - Cq * d) / det, (B * d - A * e) / det
    k = float(C[2, 2]) + d * cx + e * cy
    if k >= 0:
        return None
    # eigenvalues of the 2x2 block, ascending: the smaller one belongs to the major axis
    mean, diff = 0.5 * (A + Cq), math.hypot(0.5 * (A - Cq), B)
    lam_small, lam_big = mean - diff, mean + diff
    if lam_small <= 0:
        return None
    a_ax, b_ax = math.sqrt(-k / lam_small), math.sqrt(-k / lam_big)
    angle = 0.5 * math.atan2(2.0 * B, A - Cq) + math.pi / 2  # direction of the major axis
    res = 0.0
    n = 0
    if residuals is not None:
        res, n = float(np.sqrt(np.mean(residuals * residuals))), int(residuals.size)
    elif x is not None and y is not None:
        dist = sampson_distances(C, x, y)
        res, n = float(np.sqrt(np.mean(dist * dist))), int(x.size)
    return Ellipse(np.array([cx, cy]), a_ax, b_ax, angle, C, res, n)


def circle_normals_from_conic(C_px: FloatArray, K: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """The two possible unit normals (pointing towards the camera) of a circle's supporting plane,
    from its image conic and the intrinsics (Shiu & Ahmad 1989; Kanatani). The true one is fixed
    by a second view. Returns None when the conic is not an ellipse."""
    Q = K.T @ C_px @ K
    lam, V = np.linalg.eigh(Q)
    if np.sum(lam > 0) == 1:
        lam, V = -lam, V
    order = np.argsort(-lam)  # l1 >= l2 > 0 > l3
    lam, V = lam[order], V[:, order]
    l1, l2, l3 = lam
    if not (l1 >= l2 > 0 > l3):
        return None
    g = math.sqrt(max((l1 - l2) / (l1 - l3), 0.0))
    h = math.sqrt(max((l2 - l3) / (l1 - l3), 0.0))
    out = []
    for sgn in (1.0, -1.0):
        n = V @ np.array([sgn * g, 0.0, h])
        n = n / np.linalg.norm(n)
        if n[2] > 0:
            n = -n
        out.append(np.asarray(n, dtype=np.float64))
    return out[0], out[1]


def projected_center_from_normal(C_px: FloatArray, K: FloatArray, normal_cam: FloatArray) -> FloatArray:
    """Image of the circle's centre: the pole of the plane's vanishing line ``l = K^-T n`` with
    respect to the image conic (pole-polar relation). (2,) pixels."""
    # l = K^-T n for an upper-triangular K, then the pole p ~ adj(C) l (C symmetric)
    fx, s, cx, fy, cy = float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2])
    n0, n1, n2 = (float(v) for v in normal_cam)
    l0 = n0 / fx
    l1 = (n1 - s * l0) / fy
    l2 = n2 - cx * l0 - cy * l1
    a, b, d = float(C_px[0, 0]), float(C_px[0, 1]), float(C_px[0, 2])
    c, e, f = float(C_px[1, 1]), float(C_px[1, 2]), float(C_px[2, 2])
    A00, A01, A02 = c * f - e * e, d * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - d * d, b * d - a * e, a * c - b * b
    p0 = A00 * l0 + A01 * l1 + A02 * l2
    p1 = A01 * l0 + A11 * l1 + A12 * l2
    p2 = A02 * l0 + A12 * l1 + A22 * l2
    return np.array([p0 / p2, p1 / p2])


def _direct_fit_batch(X: FloatArray, Y: FloatArray, W: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Weighted direct ellipse fits of E point sets at once: X, Y, W are (E, R) (weight 0 = unused
    point). Returns conics (E, 3, 3) (normalised) and a validity mask (E,). The 3x3 algebra is in
    closed form (:mod:`hil.vision.sym3`): the same fit as :func:`fit_conic_direct`."""
    n = W.sum(axis=1)
    ok = n >= 6
    n = np.where(ok, n, 1.0)
    mx = (W * X).sum(axis=1) / n
    my = (W * Y).sum(axis=1) / n
    xc, yc = X - mx[:, None], Y - my[:, None]
    s = np.sqrt((W * (xc * xc + yc * yc)).sum(axis=1) / (2.0 * n))
    s = np.where(s > 0, s, 1.0)
    xn, yn = xc / s[:, None], yc / s[:, None]
    D = np.stack([xn * xn, xn * yn, yn * yn, xn, yn, np.ones_like(xn)], axis=1)  # (E, 6, R)
    S = (D * W[:, None, :]) @ np.transpose(D, (0, 2, 1))
    S1, S2, S3 = S[:, :3, :3], S[:, :3, 3:], S[:, 3:, 3:]
    det3 = det_sym3(S3)
    ok &= np.abs(det3) > 1e-12
    # T = -S3^-1 S2^T (Halir & Flusser); reduced scatter Sr = S1 + S2 T = S1 - S2 S3^-1 S2^T
    T = adj_sym3(S3) @ np.transpose(S2, (0, 2, 1)) * (-1.0 / np.where(ok, det3, 1.0))[:, None, None]
    Sr = S1 + S2 @ T
    Sr = 0.5 * (Sr + np.transpose(Sr, (0, 2, 1)))
    Sr = np.where(np.isfinite(Sr), Sr, 0.0)
    tr = Sr[:, 0, 0] + Sr[:, 1, 1] + Sr[:, 2, 2]
    pos = ok & (tr > 0)
    Sr = np.where(pos[:, None, None], Sr + (1e-12 * tr)[:, None, None] * np.eye(3), np.eye(3))
    # the fit is the generalised eigenvector Sr a = lambda C1 a with lambda > 0 (4ac - b^2 > 0)
    a1, _, good = ellipse_eigvec(Sr)
    ok &= pos & good & (4.0 * a1[:, 0] * a1[:, 2] - a1[:, 1] ** 2 > 0)
    a2 = np.einsum("eij,ej->ei", T, a1)
    Cn = np.empty((X.shape[0], 3, 3))
    Cn[:, 0, 0], Cn[:, 1, 1], Cn[:, 2, 2] = a1[:, 0], a1[:, 2], a2[:, 2]
    Cn[:, 0, 1] = Cn[:, 1, 0] = 0.5 * a1[:, 1]
    Cn[:, 0, 2] = Cn[:, 2, 0] = 0.5 * a2[:, 0]
    Cn[:, 1, 2] = Cn[:, 2, 1] = 0.5 * a2[:, 1]
    N = np.zeros((X.shape[0], 3, 3))
    N[:, 0, 0] = N[:, 1, 1] = 1.0 / s
    N[:, 0, 2], N[:, 1, 2], N[:, 2, 2] = -mx / s, -my / s, 1.0
    C = np.transpose(N, (0, 2, 1)) @ Cn @ N
    C /= np.sqrt(np.einsum("eij,eij->e", C, C))[:, None, None]
    return C, ok


def _sampson_batch(C: FloatArray, X: FloatArray, Y: FloatArray, P: FloatArray | None = None) -> FloatArray:
    """Sampson distances (E, R) of the points (X, Y) to their conics C (E, 3, 3); ``P``: the points
    as homogeneous columns (E, 3, R) when already stacked."""
    if P is None:
        P = _homogeneous(X, Y)
    G = C @ P  # the gradients (halved) and the third row
    alg = (P * G).sum(axis=1)
    gx, gy = G[:, 0], G[:, 1]
    return np.asarray(alg / np.maximum(2.0 * np.sqrt(gx * gx + gy * gy), 1e-300), dtype=np.float64)


def _homogeneous(X: FloatArray, Y: FloatArray) -> FloatArray:
    P = np.empty((X.shape[0], 3, X.shape[1]))
    P[:, 0], P[:, 1], P[:, 2] = X, Y, 1.0
    return P


@dataclass(frozen=True)
class EllipseArrays:
    """E fitted ellipses as arrays: conics (E, 3, 3), centres (E, 2), semi-axes a >= b (E,),
    major-axis angles (E,), RMS Sampson residuals (E,), points used (E,), and ``good`` (E,): the
    fit is a real ellipse (the other rows are meaningless)."""

    conic: FloatArray
    center_px: FloatArray
    a_px: FloatArray
    b_px: FloatArray
    angle_rad: FloatArray
    residual_rms_px: FloatArray
    n_points: NDArray[np.int64]
    good: NDArray[np.bool_]

    def ellipse(self, i: int) -> Ellipse | None:
        if not self.good[i]:
            return None
        return Ellipse(self.center_px[i].copy(), float(self.a_px[i]), float(self.b_px[i]),
                       float(self.angle_rad[i]), self.conic[i], float(self.residual_rms_px[i]),
                       int(self.n_points[i]))

    def ellipses(self, rows: NDArray[np.intp]) -> list[Ellipse]:
        """:meth:`ellipse` of each of ``rows`` (all of them good), built with a few array calls
        (and :func:`hil.vision.frozen.frozen_instance`)."""
        centers, conics = self.center_px[rows], self.conic[rows]
        a, b = self.a_px[rows].tolist(), self.b_px[rows].tolist()
        ang, res = self.angle_rad[rows].tolist(), self.residual_rms_px[rows].tolist()
        n = self.n_points[rows].tolist()
        return [
            frozen_instance(Ellipse, {
                "center_px": centers[k], "a_px": a[k], "b_px": b[k], "angle_rad": ang[k],
                "conic": conics[k], "residual_rms_px": res[k], "n_points": n[k],
            })
            for k in range(len(a))
        ]


def fit_ellipse_arrays(X: FloatArray, Y: FloatArray, M: NDArray[np.bool_]) -> EllipseArrays:
    """Robust direct ellipse fits of E point sets (X, Y (E, R) px, M the used points): a fit, the
    points beyond 3 MAD of the Sampson distances (and 0.05 px) dropped, a re-fit. Same result as
    fitting each set on its own. By the compiled kernel when it is selected
    (:mod:`hil.vision.kernel`; the same results to rounding), else :func:`fit_ellipse_arrays_numpy`."""
    return fit_ellipse_arrays_used(X, Y, M)[0]


def fit_ellipse_arrays_used(
    X: FloatArray, Y: FloatArray, M: NDArray[np.bool_]
) -> tuple[EllipseArrays, NDArray[np.bool_]]:
    """:func:`fit_ellipse_arrays` and the points of each final fit (E, R) (the re-fit's inliers)."""
    k = kernel.active()
    if k is None:
        return fit_ellipse_arrays_numpy(X, Y, M)
    E, R = X.shape
    C, centers = np.empty((E, 3, 3)), np.empty((E, 2))
    a, b, ang, res = np.empty(E), np.empty(E), np.empty(E), np.empty(E)
    n_pts, good, used = np.empty(E, dtype=np.int64), np.empty(E, dtype=bool), np.empty((E, R), dtype=bool)
    k.fit_ellipses(np.ascontiguousarray(X, dtype=np.float64), np.ascontiguousarray(Y, dtype=np.float64),
                   np.ascontiguousarray(M, dtype=np.bool_), C, centers, a, b, ang, res, n_pts, good, used)
    return EllipseArrays(C, centers, a, b, ang, res, n_pts, good), used


def fit_ellipse_arrays_numpy(
    X: FloatArray, Y: FloatArray, M: NDArray[np.bool_]
) -> tuple[EllipseArrays, NDArray[np.bool_]]:
    """The numpy reference of :func:`fit_ellipse_arrays_used` (batched array operations)."""
    W = M.astype(np.float64)
    C, ok = _direct_fit_batch(X, Y, W)
    P = _homogeneous(X, Y)
    d = np.abs(_sampson_batch(C, X, Y, P))
    cnt = np.count_nonzero(M, axis=1)
    srt = np.sort(np.where(M, d, np.inf), axis=1)
    mad = srt[np.arange(srt.shape[0]), cnt // 2] * 1.4826 + 1e-3
    keep = M & (d <= np.maximum(3.0 * mad, 0.05)[:, None])
    n_keep = np.count_nonzero(keep, axis=1)
    refit = (n_keep < cnt) & (n_keep >= 6)
    if refit.any():
        W2 = np.where(refit[:, None], keep, M).astype(np.float64)
        C2, ok2 = _direct_fit_batch(X, Y, W2)
        C = np.where(refit[:, None, None], C2, C)
        ok = np.where(refit, ok & ok2, ok)
        M = W2 > 0
        d = np.abs(_sampson_batch(C, X, Y, P))
    # ellipse parameters of all conics at once (closed forms of ellipse_from_conic)
    C = np.where((C[:, 0, 0] + C[:, 1, 1] < 0)[:, None, None], -C, C)
    A, B, Cq = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    dd, ee, ff = C[:, 0, 2], C[:, 1, 2], C[:, 2, 2]
    det = A * Cq - B * B
    with np.errstate(divide="ignore", invalid="ignore"):
        cx, cy = (B * ee - Cq * dd) / det, (B * dd - A * ee) / det
        k = ff + dd * cx + ee * cy
        mean, diff = 0.5 * (A + Cq), np.hypot(0.5 * (A - Cq), B)
        lam_s, lam_b = mean - diff, mean + diff
        a_ax, b_ax = np.sqrt(-k / lam_s), np.sqrt(-k / lam_b)
    angle = 0.5 * np.arctan2(2.0 * B, A - Cq) + math.pi / 2
    good = ok & (det > 0) & (k < 0) & (lam_s > 0) & np.isfinite(a_ax) & np.isfinite(b_ax)
    n_pts = np.count_nonzero(M, axis=1)
    res = np.sqrt(np.where(M, d * d, 0.0).sum(axis=1) / np.maximum(n_pts, 1))
    centers = np.empty((C.shape[0], 2))
    centers[:, 0], centers[:, 1] = cx, cy
    return EllipseArrays(C, centers, a_ax, b_ax, angle, res, n_pts, good), M


def fit_ellipses_robust_batch(X: FloatArray, Y: FloatArray, M: NDArray[np.bool_]) -> list[Ellipse | None]:
    """:func:`fit_ellipse_arrays` as one :class:`Ellipse` (or None: not an ellipse) per point set."""
    if X.shape[0] == 0:
        return []
    fits = fit_ellipse_arrays(X, Y, M)
    return [fits.ellipse(i) for i in range(X.shape[0])]


def circle_normals_from_conics(
    C_px: FloatArray, K: FloatArray
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """:func:`circle_normals_from_conic` for a stack of conics (P, 3, 3) seen by one camera ``K``:
    the two candidate normals (P, 3) each and a validity mask (P,) (False: not an ellipse)."""
    if C_px.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=bool)
    return circle_normals_from_cones(K.T @ C_px @ K)


def circle_normals_from_cones(Q: FloatArray) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """The two candidate circle-plane normals of each cone ``Q = K^T C K`` (P, 3, 3) (normalised
    camera coordinates; Shiu & Ahmad 1989), and a validity mask. See :func:`circle_normals_from_conic`."""
    lam, V = np.linalg.eigh(Q)  # ascending
    flip = np.sum(lam > 0, axis=1) == 1
    # descending order l1 >= l2 > 0 > l3: reversed, or (after negating a one-positive spectrum)
    # the negated ascending order
    l1 = np.where(flip, -lam[:, 0], lam[:, 2])
    l2 = np.where(flip, -lam[:, 1], lam[:, 1])
    l3 = np.where(flip, -lam[:, 2], lam[:, 0])
    v1 = np.where(flip[:, None], V[:, :, 0], V[:, :, 2])
    v3 = np.where(flip[:, None], V[:, :, 2], V[:, :, 0])
    ok = (l1 >= l2) & (l2 > 0) & (l3 < 0)
    den = np.where(ok, l1 - l3, 1.0)
    g = np.sqrt(np.maximum((l1 - l2) / den, 0.0))
    h = np.sqrt(np.maximum((l2 - l3) / den, 0.0))
    a, b = v1 * g[:, None], v3 * h[:, None]
    n = np.stack([b + a, b - a])  # the signs +g and -g, (2, P, 3)
    n = n / np.sqrt(np.sum(n * n, axis=2, keepdims=True))
    n = np.where(n[:, :, 2:] > 0, -n, n)  # towards the camera
    return n[0], n[1], np.asarray(ok, dtype=np.bool_)


def poles_of_lines(C_px: FloatArray, lines: FloatArray) -> FloatArray:
    """Pole of each line ``l`` (N, 3) with respect to its conic (N, 3, 3): ``p ~ adj(C) l`` (C
    symmetric), as (N, 2) pixels."""
    l0, l1, l2 = lines[:, 0], lines[:, 1], lines[:, 2]
    a, b, d = C_px[:, 0, 0], C_px[:, 0, 1], C_px[:, 0, 2]
    c, e, f = C_px[:, 1, 1], C_px[:, 1, 2], C_px[:, 2, 2]
    A00, A01, A02 = c * f - e * e, d * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - d * d, b * d - a * e, a * c - b * b
    p0 = A00 * l0 + A01 * l1 + A02 * l2
    p1 = A01 * l0 + A11 * l1 + A12 * l2
    p2 = A02 * l0 + A12 * l1 + A22 * l2
    return np.stack([p0 / p2, p1 / p2], axis=1)


def vanishing_lines(K: FloatArray, normals: FloatArray) -> FloatArray:
    """``l = K^-T n`` for an upper-triangular K and normals (N, 3) -> (N, 3)."""
    fx, s, cx, fy, cy = float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2])
    l0 = normals[:, 0] / fx
    l1 = (normals[:, 1] - s * l0) / fy
    l2 = normals[:, 2] - cx * l0 - cy * l1
    return np.stack([l0, l1, l2], axis=1)


def projected_centers_from_normals(C_px: FloatArray, K: FloatArray, normals: FloatArray) -> FloatArray:
    """:func:`projected_center_from_normal` for stacks: conics (P, 3, 3), normals (P, 3) -> (P, 2)."""
    return poles_of_lines(C_px, vanishing_lines(K, normals))
