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
  (Viete) formula and refined by Newton steps; the vector is a column of the rank-one adjugate
  of ``S - lambda C1``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


#: the upper triangle (00, 01, 02, 11, 12, 22) and the diagonal, as index arrays
_ROWS, _COLS = np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2])
_DIAG = np.arange(3)


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


def ellipse_eigvec(S: FloatArray) -> tuple[FloatArray, FloatArray, BoolArray]:
    """The generalised eigenvector ``a`` of ``S a = lambda C1 a`` with ``lambda > 0``, where
    ``C1 = [[0, 0, 2], [0, -1, 0], [2, 0, 0]]`` (``a^T C1 a = 4 a0 a2 - a1^2``, the ellipse
    constraint of Fitzgibbon 1999) and S (P, 3, 3) is symmetric positive definite (the reduced
    scatter matrix of Halir & Flusser 1998).

    For a positive definite S the pencil has exactly one positive eigenvalue (C1 has one positive
    eigenvalue); it is the largest root of the cubic ``det(S - lambda C1) = -4 lambda^3 +
    4 (s02 - s11) lambda^2 + (s00 s22 - 4 s01 s12 + 4 s11 s02 - s02^2) lambda + det(S)``, all of
    whose roots are real: the trigonometric (Viete) form, then two Newton steps (the small root
    of a good fit is otherwise only accurate to ~eps x the largest root). The vector is the column
    of ``adj(S - lambda C1)`` (rank one: every column is a multiple of the null vector) with the
    largest diagonal entry.

    Returns ``a`` (P, 3) (unnormalised, sign arbitrary), lambda (P,) and a mask (P,): S positive
    definite, lambda > 0 and ``a`` not zero (the other rows are meaningless).
    """
    P = S.shape[0]
    s00, s01, s02, s11, s12, s22 = S[:, _ROWS, _COLS].T  # contiguous (P,) rows
    det = s00 * (s11 * s22 - s12 * s12) - s01 * (s01 * s22 - s12 * s02) + s02 * (s01 * s12 - s11 * s02)
    pd = (s00 > 0) & (s00 * s11 - s01 * s01 > 0) & (det > 0)
    # monic form lambda^3 + c2 lambda^2 + c1 lambda + c0; depressed t^3 + 3 p t + 2 q, lambda = t - c2/3
    c2 = s11 - s02
    c1 = -0.25 * (s00 * s22 - 4.0 * s01 * s12 + 4.0 * s11 * s02 - s02 * s02)
    c0 = -0.25 * det
    sh = c2 / 3.0
    p = c1 / 3.0 - sh * sh
    q = sh * sh * sh - 0.5 * c1 * sh + 0.5 * c0
    m = np.sqrt(np.maximum(-p, 0.0))  # p <= 0 for three real roots (clamped against rounding)
    m3 = m * m * m
    cos3 = np.clip(np.divide(-q, m3, out=np.zeros(P), where=m3 > 0), -1.0, 1.0)
    lam = 2.0 * m * np.cos(np.arccos(cos3) / 3.0) - sh
    for _ in range(2):
        f = ((lam + c2) * lam + c1) * lam + c0
        df = (3.0 * lam + 2.0 * c2) * lam + c1
        lam = lam - np.divide(f, df, out=np.zeros(P), where=df != 0)
    # adjugate of M = S - lambda C1: m02 = s02 - 2 lambda, m11 = s11 + lambda
    m02, m11 = s02 - 2.0 * lam, s11 + lam
    adj = np.array([
        [m11 * s22 - s12 * s12, m02 * s12 - s01 * s22, s01 * s12 - m02 * m11],
        [m02 * s12 - s01 * s22, s00 * s22 - m02 * m02, s01 * m02 - s00 * s12],
        [s01 * s12 - m02 * m11, s01 * m02 - s00 * s12, s00 * m11 - s01 * s01],
    ])  # (3, 3, P), symmetric
    k = np.argmax(np.abs(adj[_DIAG, _DIAG]), axis=0)
    a = adj[:, k, np.arange(P)].T
    ok = pd & (lam > 0) & np.any(a != 0, axis=1)
    return np.asarray(a, dtype=np.float64), np.asarray(lam, dtype=np.float64), np.asarray(ok, dtype=np.bool_)
