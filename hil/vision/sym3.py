"""Closed-form algebra of stacks of small symmetric 3x3 matrices, element-wise over the stack.

For the few dozen matrices of one stereo pair, ``np.linalg`` (det, solve, cholesky, eigh) costs
10-70 us per call in argument checks and LAPACK set-up, against well under 1 us per element-wise
operation on a (P,) column: these forms do the same arithmetic with element-wise operations on the
matrices' entries. Every function takes a stack ``(P, 3, 3)`` of symmetric matrices (only the
upper triangle is read) and works on each matrix on its own.

Methods:
- determinant and adjugate: the cofactor expansion;
- the ellipse-constrained generalised eigenvector (Fitzgibbon, Pilu & Fisher 1999, eq 7; the
  reduced form of Halir & Flusser 1998): the one positive root of the characteristic cubic
  ``det(S - lambda C1) = 0``, found as the largest of its three real roots by the trigonometric
  (Viete) formula, refined by Newton steps; the vector is the null vector of ``S - lambda C1`` as
  the largest cross product of two of its rows;
- the symmetric eigen-decomposition: eigenvalues by the trigonometric formula for the symmetric
  3x3 case (Smith 1961, "Eigenvalues of a symmetric 3x3 matrix", CACM 4(4)), the eigenvector of
  the eigenvalue furthest from the other two as a cross product of rows, the other two from the
  2x2 problem in the plane orthogonal to it (its angle by ``atan2``, exact for close eigenvalues),
  the approach of Eberly, "A Robust Eigensolver for 3x3 Symmetric Matrices" (2014).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def _entries(S: FloatArray) -> tuple[FloatArray, ...]:
    return S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]


def det_sym3(S: FloatArray) -> FloatArray:
    """Determinants (P,) of symmetric matrices (P, 3, 3)."""
    a, b, c, d, e, f = _entries(S)
    return np.asarray(a * (d * f - e * e) - b * (b * f - c * e) + c * (b * e - c * d), dtype=np.float64)


def adj_sym3(S: FloatArray) -> FloatArray:
    """Adjugates (P, 3, 3) of symmetric matrices (P, 3, 3): ``S adj(S) = det(S) I``."""
    a, b, c, d, e, f = _entries(S)
    A00, A01, A02 = d * f - e * e, c * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - c * c, b * c - a * e, a * d - b * b
    out = np.empty_like(S)
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = A00, A01, A02
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = A01, A11, A12
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = A02, A12, A22
    return out


def _cross(u: FloatArray, v: FloatArray) -> FloatArray:
    """Row-wise cross products of (P, 3) stacks (``np.cross`` costs ~20x more on small stacks)."""
    out = np.empty_like(u)
    out[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    out[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    out[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    return out


def _null_vectors(M: FloatArray) -> FloatArray:
    """Per matrix (P, 3, 3) of rank <= 2, a null vector (P, 3): the largest of the cross products
    of two of its rows (unnormalised)."""
    r0, r1, r2 = M[:, 0, :], M[:, 1, :], M[:, 2, :]
    c01, c02, c12 = _cross(r0, r1), _cross(r0, r2), _cross(r1, r2)
    n01, n02, n12 = (np.einsum("pi,pi->p", c, c) for c in (c01, c02, c12))
    best = np.where((n02 > n01)[:, None], c02, c01)
    return np.asarray(np.where((n12 > np.maximum(n01, n02))[:, None], c12, best), dtype=np.float64)


def _largest_real_root(c2: FloatArray, c1: FloatArray, c0: FloatArray) -> FloatArray:
    """Largest root of ``x^3 + c2 x^2 + c1 x + c0`` whose three roots are real (trigonometric form;
    a tiny negative discriminant from rounding is clamped)."""
    s = c2 / 3.0
    p = c1 / 3.0 - s * s  # depressed cubic t^3 + 3 p t + 2 q, x = t - s
    q = s * s * s - 0.5 * c1 * s + 0.5 * c0
    m = np.sqrt(np.maximum(-p, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        cos3 = np.clip(np.where(m > 0, -q / (m * m * m), 0.0), -1.0, 1.0)
    return np.asarray(2.0 * m * np.cos(np.arccos(cos3) / 3.0) - s, dtype=np.float64)


def ellipse_eigvec(S: FloatArray) -> tuple[FloatArray, FloatArray, BoolArray]:
    """The generalised eigenvector ``a`` of ``S a = lambda C1 a`` with ``lambda > 0``, where
    ``C1 = [[0, 0, 2], [0, -1, 0], [2, 0, 0]]`` (``a^T C1 a = 4 a0 a2 - a1^2``, the ellipse
    constraint of Fitzgibbon 1999) and S (P, 3, 3) is symmetric positive definite (the reduced
    scatter matrix of Halir & Flusser 1998).

    For a positive definite S the pencil has exactly one positive eigenvalue (C1 has one positive
    eigenvalue); it is the largest root of the cubic ``det(S - lambda C1) = -4 lambda^3 +
    4 (s02 - s11) lambda^2 + (s00 s22 - 4 s01 s12 + 4 s11 s02 - s02^2) lambda + det(S)``.

    Returns ``a`` (P, 3) (unnormalised, sign arbitrary), lambda (P,) and a mask (P,): S positive
    definite, lambda > 0 and ``a`` not zero (the other rows are meaningless).
    """
    s00, s01, s02, s11, s12, s22 = _entries(S)
    det = det_sym3(S)
    pd = (s00 > 0) & (s00 * s11 - s01 * s01 > 0) & (det > 0)
    # monic form: lambda^3 + c2 lambda^2 + c1 lambda + c0
    c2 = s11 - s02
    c1 = -0.25 * (s00 * s22 - 4.0 * s01 * s12 + 4.0 * s11 * s02 - s02 * s02)
    c0 = -0.25 * det
    lam = _largest_real_root(c2, c1, c0)
    for _ in range(2):  # Newton steps: the trigonometric root is accurate to ~eps x the largest root
        f = ((lam + c2) * lam + c1) * lam + c0
        df = (3.0 * lam + 2.0 * c2) * lam + c1
        lam = lam - np.where(df != 0, f / np.where(df != 0, df, 1.0), 0.0)
    M = S.copy()
    M[:, 0, 2] -= 2.0 * lam
    M[:, 2, 0] = M[:, 0, 2]
    M[:, 1, 1] += lam
    a = _null_vectors(M)
    ok = pd & (lam > 0) & (np.einsum("pi,pi->p", a, a) > 0)
    return a, lam, np.asarray(ok, dtype=np.bool_)


def eigh_sym3(S: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eigenvalues (P, 3), ascending, and unit eigenvectors (P, 3, 3) (column k for eigenvalue k)
    of symmetric matrices (P, 3, 3), as ``np.linalg.eigh`` (eigenvector signs may differ)."""
    a, b, c, d, e, f = _entries(S)
    P = S.shape[0]
    q = (a + d + f) / 3.0
    p1 = b * b + c * c + e * e
    p2 = (a - q) ** 2 + (d - q) ** 2 + (f - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    pz = p > 0
    pi = np.where(pz, p, 1.0)
    # B = (S - q I) / p, r = det(B) / 2 in [-1, 1]
    Ba, Bd, Bf = (a - q) / pi, (d - q) / pi, (f - q) / pi
    Bb, Bc, Be = b / pi, c / pi, e / pi
    r = 0.5 * (Ba * (Bd * Bf - Be * Be) - Bb * (Bb * Bf - Bc * Be) + Bc * (Bb * Be - Bc * Bd))
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    l_hi = q + 2.0 * p * np.cos(phi)
    l_lo = q + 2.0 * p * np.cos(phi + 2.0 * math.pi / 3.0)
    l_mid = 3.0 * q - l_hi - l_lo
    # the eigenvalue furthest from the other two is well separated: its vector from a null space
    hi_isolated = (l_hi - l_mid) >= (l_mid - l_lo)
    l_iso = np.where(hi_isolated, l_hi, l_lo)
    M = S.copy()
    M[:, 0, 0] -= l_iso
    M[:, 1, 1] -= l_iso
    M[:, 2, 2] -= l_iso
    u = _null_vectors(M)
    nu = np.sqrt(np.einsum("pi,pi->p", u, u))
    degenerate = ~(nu > 0) | ~pz  # a multiple of the identity: any basis
    u = np.where(degenerate[:, None], np.array([0.0, 0.0, 1.0]), u / np.where(nu > 0, nu, 1.0)[:, None])
    # an orthonormal basis (v, w) of the plane orthogonal to u
    pick_x = np.abs(u[:, 0]) <= np.abs(u[:, 1])
    t = np.where(pick_x[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    v = _cross(u, t)
    v /= np.sqrt(np.einsum("pi,pi->p", v, v))[:, None]
    w = _cross(u, v)
    Sv, Sw = np.einsum("pij,pj->pi", S, v), np.einsum("pij,pj->pi", S, w)
    m00, m01, m11 = np.einsum("pi,pi->p", v, Sv), np.einsum("pi,pi->p", v, Sw), np.einsum("pi,pi->p", w, Sw)
    ang = 0.5 * np.arctan2(2.0 * m01, m00 - m11)  # the larger eigenvalue's direction in (v, w)
    ca, sa = np.cos(ang), np.sin(ang)
    x_big = ca[:, None] * v + sa[:, None] * w
    x_small = -sa[:, None] * v + ca[:, None] * w
    mean2, rad2 = 0.5 * (m00 + m11), np.hypot(0.5 * (m00 - m11), m01)
    lam = np.empty((P, 3))
    vec = np.empty((P, 3, 3))
    h = hi_isolated[:, None]
    lam[:, 0] = np.where(hi_isolated, mean2 - rad2, l_iso)
    lam[:, 1] = np.where(hi_isolated, mean2 + rad2, mean2 - rad2)
    lam[:, 2] = np.where(hi_isolated, l_iso, mean2 + rad2)
    vec[:, :, 0] = np.where(h, x_small, u)
    vec[:, :, 1] = np.where(h, x_big, x_small)
    vec[:, :, 2] = np.where(h, u, x_big)
    return lam, vec
