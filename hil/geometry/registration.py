"""Paired-point rigid registration: Horn's quaternion method and the SVD (Arun/Umeyama) method.

Both solve ``min_{R,t} sum_i w_i |R m_i + t - f_i|^2`` for paired points ``m_i`` (MOVING) and
``f_i`` (FIXED) and return ``T_fixed_from_moving`` (``f ≈ T.apply(m)``), the per-point residuals
and the fiducial registration error (FRE, RMS of the residuals). They agree to rounding error;
tests cross-check them.

Input validation is shared: at least 3 pairs, equal counts, finite values, and neither point set
collinear or coincident (such a set does not fix a rotation). Every failure is a typed
:class:`hil.errors.GeometryError` (or its subclass :class:`DegenerateConfigurationError`) raised
before any numpy operation could emit a warning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry import native
from hil.geometry.transform import RigidTransform, as_points, quaternion_to_matrix

FloatArray = NDArray[np.float64]

#: Relative singular-value threshold below which a centred point set counts as collinear.
COLLINEAR_REL_TOL = 1e-6
#: Absolute spread (mm) below which a point set counts as coincident (all points at one place).
COINCIDENT_TOL_MM = 1e-9
#: Largest coordinate magnitude registered, mm (a kilometre is 1e6 mm: no rig measures beyond this,
#: and below it every sum and product of Horn's method stays finite; beyond it numpy's eigen-solver
#: met infinities and raised LinAlgError).
MAX_COORDINATE_MM = 1e9

_EYE3 = np.eye(3)
_EYE3.setflags(write=False)


@dataclass(frozen=True)
class Registration:
    """Result of a paired-point rigid registration.

    Attributes:
        T_fixed_from_moving: maps MOVING points into FIXED's frame.
        residuals_mm: (N,) distances ``|T m_i - f_i|`` in mm, in input order.
        fre_rms_mm: fiducial registration error, RMS of the residuals (weighted RMS when weights
            were given: ``sqrt(sum w r^2 / sum w)``).
        method: ``"horn"`` or ``"svd"``.
    """

    T_fixed_from_moving: RigidTransform
    residuals_mm: FloatArray
    fre_rms_mm: float
    method: str


def check_point_configuration(points: ArrayLike, name: str = "points", min_points: int = 3) -> FloatArray:
    """Validate a point set that must fix a rigid transform; return it as (N, 3) float64.

    Raises:
        GeometryError: wrong shape, NaN/inf, or fewer than ``min_points`` points.
        DegenerateConfigurationError: all points coincident, or all on one line.
    """
    return _check_configuration(as_points(points, name), name, min_points)


def _check_configuration(pts: FloatArray, name: str, min_points: int = 3) -> FloatArray:
    """:func:`check_point_configuration` of points :func:`as_points` already validated."""
    n = pts.shape[0]
    if n < min_points:
        raise GeometryError(f"{name}: {n} point(s) given, at least {min_points} are needed")
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    scale = float(np.max(np.abs(pts))) if n else 0.0
    if sv[0] <= COINCIDENT_TOL_MM * max(1.0, scale):
        raise DegenerateConfigurationError(f"{name}: all points coincide")
    if sv[1] <= COLLINEAR_REL_TOL * sv[0]:
        raise DegenerateConfigurationError(
            f"{name}: points are collinear (they do not fix the rotation about their common line)"
        )
    return pts


def _validate(
    fixed: ArrayLike, moving: ArrayLike, weights: ArrayLike | None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    f = as_points(fixed, "fixed")
    m = as_points(moving, "moving")
    for pts, name in ((f, "fixed"), (m, "moving")):
        far = float(np.abs(pts).max()) if pts.size else 0.0
        if far > MAX_COORDINATE_MM:
            raise GeometryError(f"{name} has a coordinate of {far:.3g} mm, beyond the "
                                f"{MAX_COORDINATE_MM:g} mm any rig measures (wrong units?)")
    if f.shape[0] != m.shape[0]:
        raise GeometryError(
            f"fixed has {f.shape[0]} points but moving has {m.shape[0]}; "
            "paired registration needs equal counts"
        )
    if weights is None:
        w = np.ones(f.shape[0])
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape[0] != f.shape[0]:
            raise GeometryError(f"{w.shape[0]} weights given for {f.shape[0]} point pairs")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise GeometryError("weights must be finite and non-negative")
        if int(np.count_nonzero(w > 0)) < 3:
            raise GeometryError("at least 3 point pairs need a positive weight")
    if weights is None:   # every pair takes part
        _check_configuration(f, "fixed")
        _check_configuration(m, "moving")
    else:
        active = w > 0
        _check_configuration(f[active], "fixed")
        _check_configuration(m[active], "moving")
    return f, m, w


def _weighted_cross_covariance(
    f: FloatArray, m: FloatArray, w: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted centroids and ``A = sum_i w_i (m_i - m̄)(f_i - f̄)^T / sum w`` (seed 000 eq 17)."""
    wn = w / w.sum()
    f_bar = wn @ f
    m_bar = wn @ m
    A = ((m - m_bar) * wn[:, None]).T @ (f - f_bar)
    return f_bar, m_bar, A


def _finish(
    f: FloatArray,
    m: FloatArray,
    w: FloatArray,
    R: FloatArray,
    f_bar: FloatArray,
    m_bar: FloatArray,
    method: str,
) -> Registration:
    t = f_bar - R @ m_bar
    T = RigidTransform(R, t)
    residuals = np.linalg.norm(m @ T.R.T + T.t - f, axis=1)
    fre = math.sqrt(float(w @ residuals**2) / float(w.sum()))
    residuals.setflags(write=False)
    return Registration(T_fixed_from_moving=T, residuals_mm=residuals, fre_rms_mm=fre, method=method)


def horn_matrix(A: ArrayLike) -> FloatArray:
    """Horn's symmetric 4x4 matrix from the cross-covariance ``A`` (seed 000 eqs 18-20).

    ``B = A - A^T``, ``Δ = [B23, B31, B12]^T`` and
    ``C = [[tr A, Δ^T], [Δ, A + A^T - tr(A) I3]]``. (The paper prints ``B13`` as the third
    component of Δ; the antisymmetric part has only three independent entries and Horn/Besl-McKay
    use ``B12``, which is what makes the eigenvector the optimal rotation.)
    """
    A_ = np.asarray(A, dtype=np.float64)
    B = A_ - A_.T
    delta = np.array([B[1, 2], B[2, 0], B[0, 1]])
    tr = float(np.trace(A_))
    C = np.empty((4, 4))
    C[0, 0] = tr
    C[0, 1:] = delta
    C[1:, 0] = delta
    C[1:, 1:] = A_ + A_.T - tr * _EYE3
    return C


def register_horn(fixed: ArrayLike, moving: ArrayLike, weights: ArrayLike | None = None) -> Registration:
    """Horn's closed-form quaternion registration exactly as seed 000 eqs 17-21 describe it.

    ``A = sum w_i (m_i - m̄)(f_i - f̄)^T`` (eq 17, moving ``p`` = the paper's optical points,
    fixed ``q`` = image points, ``Q = R P + T`` eq 13); ``C`` from eqs 18-20 (:func:`horn_matrix`);
    the unit quaternion ``q = [q0 q1 q2 q3]`` (scalar first) is the eigenvector of the largest
    eigenvalue of ``C`` (eq 21); ``R`` from the quaternion (eq 16); ``t = f̄ - R m̄``.

    Args:
        fixed: (N, 3) points in the FIXED frame, mm.
        moving: (N, 3) the same points, same order, in the MOVING frame, mm.
        weights: optional (N,) non-negative per-point weights.

    Returns:
        Registration with ``T_fixed_from_moving``.

    Raises:
        GeometryError: < 3 pairs, different counts, NaN/inf, bad weights.
        DegenerateConfigurationError: collinear or coincident points.

    (N, 3) float64 arrays (and (N,) float64 weights) are registered by the compiled code
    (:mod:`hil.geometry.native`, the same equations; it agrees with :func:`register_horn_numpy`
    to rounding) unless it declines (any input the checks refuse): then the numpy code runs.
    """
    reg = _horn_compiled(fixed, moving, weights)
    if reg is not None:
        return reg
    return register_horn_numpy(fixed, moving, weights)


def _horn_compiled(fixed: ArrayLike, moving: ArrayLike, weights: ArrayLike | None) -> Registration | None:
    """:func:`register_horn` by the compiled code, or None where the numpy code must decide (not
    built or not selected, not two (N, 3) float64 arrays of one N with None or (N,) float64
    weights, or refused by its checks)."""
    k = native.active()
    if (k is None or not isinstance(fixed, np.ndarray) or not isinstance(moving, np.ndarray)
            or fixed.dtype != np.float64 or moving.dtype != np.float64 or fixed.ndim != 2
            or fixed.shape[1] != 3 or fixed.shape != moving.shape):
        return None
    if weights is not None and (not isinstance(weights, np.ndarray) or weights.dtype != np.float64
                                or weights.shape != (fixed.shape[0],)):
        return None
    w = None if weights is None else np.ascontiguousarray(weights)
    R, t, residuals = np.empty((3, 3)), np.empty(3), np.empty(fixed.shape[0])
    fre = k.horn(np.ascontiguousarray(fixed), np.ascontiguousarray(moving), R, t, residuals, w)
    if fre < 0.0:
        return None
    residuals.setflags(write=False)
    # R is the rotation of a unit quaternion (eq 16) and every value finite: proper by construction
    return Registration(T_fixed_from_moving=RigidTransform._composed(R, t), residuals_mm=residuals,
                        fre_rms_mm=fre, method="horn")


def register_horn_numpy(fixed: ArrayLike, moving: ArrayLike,
                        weights: ArrayLike | None = None) -> Registration:
    """:func:`register_horn` in numpy (the reference of the compiled code; any weights)."""
    f, m, w = _validate(fixed, moving, weights)
    f_bar, m_bar, A = _weighted_cross_covariance(f, m, w)
    C = horn_matrix(A)
    _, vecs = np.linalg.eigh(C)  # ascending eigenvalues
    R = quaternion_to_matrix(vecs[:, -1])   # eq 16 (a fresh array)
    return _finish(f, m, w, R, f_bar, m_bar, "horn")


def register_svd(fixed: ArrayLike, moving: ArrayLike, weights: ArrayLike | None = None) -> Registration:
    """SVD registration (Arun, Huang & Blostein 1987; Umeyama 1991) with the reflection guard.

    ``A = U S V^T`` (``A`` as in :func:`register_horn`), ``R = V diag(1, 1, det(V U^T)) U^T``
    so that a reflection is never returned, even for planar point sets; ``t = f̄ - R m̄``.
    Same arguments, result and errors as :func:`register_horn`.
    """
    f, m, w = _validate(fixed, moving, weights)
    f_bar, m_bar, A = _weighted_cross_covariance(f, m, w)
    U, _, Vt = np.linalg.svd(A)
    V = Vt.T
    d = 1.0 if np.linalg.det(V @ U.T) >= 0 else -1.0
    R = V @ np.diag([1.0, 1.0, d]) @ U.T
    return _finish(f, m, w, R, f_bar, m_bar, "svd")


def register(
    fixed: ArrayLike, moving: ArrayLike, weights: ArrayLike | None = None, method: str = "horn"
) -> Registration:
    """Dispatch to :func:`register_horn` (``method="horn"``) or :func:`register_svd` (``"svd"``).

    Raises:
        GeometryError: unknown method, or any error of the chosen method.
    """
    if method == "horn":
        return register_horn(fixed, moving, weights)
    if method == "svd":
        return register_svd(fixed, moving, weights)
    raise GeometryError(f"unknown registration method {method!r} (expected 'horn' or 'svd')")
