"""Expected registration errors from the fiducial configuration (Fitzpatrick, West & Maurer 1998).

J. M. Fitzpatrick, J. B. West, C. R. Maurer Jr., "Predicting error in rigid-body point-based
registration", IEEE Trans. Med. Imaging 17(5), 1998:

- expected FRE: ``<FRE^2> ≈ (1 - 2/N) <FLE^2>``
- expected TRE at a target ``r``: ``<TRE^2(r)> ≈ <FLE^2>/N * (1 + 1/3 * sum_k d_k^2 / f_k^2)``,
  where, in the principal axes of the fiducial configuration, ``d_k`` is the distance of the target
  from axis ``k`` and ``f_k`` the RMS distance of the fiducials from axis ``k``.

``FLE`` is the RMS of the 3-D fiducial localisation error vector (for isotropic Gaussian noise of
standard deviation ``σ`` per axis, ``FLE = σ √3``). When both point sets carry localisation error,
pass the combined ``sqrt(FLE_fixed^2 + FLE_moving^2)``. The formulas are first-order: they hold
when FLE is small against the fiducial spread, and assume independent, identical, isotropic FLE.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.errors import GeometryError
from hil.geometry.registration import check_point_configuration

FloatArray = NDArray[np.float64]


def _check_fle(fle_rms_mm: float) -> float:
    fle = float(fle_rms_mm)
    if not math.isfinite(fle) or fle < 0:
        raise GeometryError(f"FLE must be a finite non-negative number of mm, got {fle_rms_mm!r}")
    return fle


def expected_tre_mm(fiducials_mm: ArrayLike, target_mm: ArrayLike, fle_rms_mm: float) -> float:
    """RMS target registration error expected at ``target_mm`` (FWM 1998, eq. for ``<TRE^2>``).

    Args:
        fiducials_mm: (N, 3) fiducial positions (either space; the configuration is what counts), mm.
        target_mm: (3,) target in the same frame as ``fiducials_mm``, mm.
        fle_rms_mm: RMS fiducial localisation error (3-D), mm.

    Returns:
        ``sqrt(<TRE^2>)`` in mm.

    Raises:
        GeometryError: fewer than 3 fiducials, NaN/inf, bad target shape or FLE.
        DegenerateConfigurationError: collinear or coincident fiducials (TRE is unbounded).
    """
    fle = _check_fle(fle_rms_mm)
    pts = check_point_configuration(fiducials_mm, "fiducials")
    target = np.asarray(target_mm, dtype=np.float64).reshape(-1)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise GeometryError(f"target must be 3 finite values, got {target_mm!r}")
    n = pts.shape[0]
    centroid = pts.mean(axis=0)
    centred = pts - centroid
    _, _, Vt = np.linalg.svd(centred)
    axes = Vt  # rows: principal axes
    proj = centred @ axes.T  # (N, 3) coordinates in the principal frame
    tproj = (target - centroid) @ axes.T
    ratio = 0.0
    for k in range(3):
        others = [j for j in range(3) if j != k]
        f2 = float(np.mean(np.sum(proj[:, others] ** 2, axis=1)))  # mean squared distance from axis k
        d2 = float(np.sum(tproj[others] ** 2))
        ratio += d2 / f2
    return math.sqrt(fle**2 / n * (1.0 + ratio / 3.0))


def expected_fre_mm(n_fiducials: int, fle_rms_mm: float) -> float:
    """RMS FRE expected for ``N`` fiducials: ``sqrt((1 - 2/N)) * FLE`` (FWM 1998).

    Raises:
        GeometryError: ``N < 3`` or a bad FLE.
    """
    fle = _check_fle(fle_rms_mm)
    if n_fiducials < 3:
        raise GeometryError(f"expected FRE needs at least 3 fiducials, got {n_fiducials}")
    return math.sqrt(1.0 - 2.0 / n_fiducials) * fle


def fle_from_fre_mm(n_fiducials: int, fre_rms_mm: float) -> float:
    """Estimate the RMS FLE from one observed FRE by inverting :func:`expected_fre_mm`.

    A single-registration estimate, noisy for small ``N``; prefer a measured FLE.

    Raises:
        GeometryError: ``N < 3`` or a bad FRE.
    """
    fre = _check_fle(fre_rms_mm)
    if n_fiducials < 3:
        raise GeometryError(f"FLE estimate needs at least 3 fiducials, got {n_fiducials}")
    return fre / math.sqrt(1.0 - 2.0 / n_fiducials)
