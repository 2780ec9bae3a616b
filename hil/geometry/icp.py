"""Point-to-point ICP (Besl & McKay 1992; seed 002 section 3.1) with a principal-axes start.

Seed 002 notes that plain ICP falls into local minima "when the rotational malposition of the
two models is relatively large" and removes most of the rotation first by "coordinate direction
fitting". The analogue here, needing no extra hardware, is a principal-directions alignment:
match the centroids and the principal axes of the two clouds, trying the four proper sign
choices of the axes (an eigenvector's sign is arbitrary), run ICP from each and keep the best.

Each iteration pairs every source point with its nearest target point (scipy ``cKDTree``),
optionally drops the worst ``trim_fraction`` of pairs (trimmed ICP, robust to outliers and partial
overlap), and solves the pairs with :func:`hil.geometry.registration.register_svd`. It stops when
the RMS of the kept pairs changes by less than ``tolerance_mm`` or after ``max_iterations``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from hil.errors import DegenerateConfigurationError, GeometryError
from hil.geometry.registration import check_point_configuration, register_svd
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]

InitMode = Literal["principal", "identity"]


@dataclass(frozen=True)
class IcpResult:
    """Outcome of :func:`icp`.

    Attributes:
        T_target_from_source: maps source points onto the target cloud.
        rms_mm: RMS nearest-neighbour distance of the kept (inlier) pairs at the end.
        iterations: ICP iterations of the returned run.
        converged: True when the RMS change fell below the tolerance before ``max_iterations``.
        inlier_fraction: fraction of source points kept in the last iteration.
        initial_candidates: how many starting poses were tried (4 for "principal", 1 otherwise).
    """

    T_target_from_source: RigidTransform
    rms_mm: float
    iterations: int
    converged: bool
    inlier_fraction: float
    initial_candidates: int


def principal_axes(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Centroid and a proper rotation whose columns are the principal axes (largest first)."""
    c = points.mean(axis=0)
    _, _, Vt = np.linalg.svd(points - c, full_matrices=False)
    E = Vt.T.copy()
    if np.linalg.det(E) < 0:
        E[:, 2] = -E[:, 2]
    return c, E


def principal_alignment_candidates(source: FloatArray, target: FloatArray) -> list[RigidTransform]:
    """The four rigid transforms that align the source's principal frame with the target's.

    Seed 002's "coordinate direction fitting" idea; the four candidates differ by 180° turns
    about the principal axes (the sign ambiguity of the eigenvectors).
    """
    cs, Es = principal_axes(source)
    ct, Et = principal_axes(target)
    out = []
    for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
        R = Et @ np.diag(np.asarray(signs, dtype=np.float64)) @ Es.T
        out.append(RigidTransform(R, ct - R @ cs))
    return out


def _run(
    source: FloatArray,
    tree: cKDTree,
    target: FloatArray,
    T0: RigidTransform,
    max_iterations: int,
    tolerance_mm: float,
    keep: int,
) -> IcpResult:
    T = T0
    prev = math.inf
    rms = math.inf
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007
        moved = T.apply(source)
        dist, idx = tree.query(moved)
        order = np.argsort(dist, kind="stable")[:keep]
        rms = math.sqrt(float(np.mean(dist[order] ** 2)))
        if abs(prev - rms) < tolerance_mm:
            converged = True
            break
        prev = rms
        try:
            step = register_svd(target[idx[order]], moved[order])
        except DegenerateConfigurationError:  # pairs collapsed onto a line of the target
            break
        T = step.T_fixed_from_moving @ T
    if not converged:  # the last step moved T after its RMS was measured
        dist, _ = tree.query(T.apply(source))
        rms = math.sqrt(float(np.mean(np.sort(dist)[:keep] ** 2)))
    return IcpResult(T, rms, it, converged, keep / source.shape[0], 1)


def icp(
    source: ArrayLike,
    target: ArrayLike,
    *,
    init: InitMode | RigidTransform = "principal",
    max_iterations: int = 100,
    tolerance_mm: float = 1e-7,
    trim_fraction: float = 0.0,
) -> IcpResult:
    """Register a source cloud onto a target cloud without known correspondences.

    Args:
        source: (N, 3) points to move (e.g. points probed on the patient), mm.
        target: (M, 3) reference cloud (e.g. the CT surface), mm.
        init: "principal" (try the four principal-axes alignments, keep the lowest final RMS),
            "identity" (plain ICP), or an explicit starting ``T_target_from_source``.
        max_iterations: iteration cap per run.
        tolerance_mm: stop when the RMS changes by less than this between iterations.
        trim_fraction: fraction in [0, 0.9] of the worst pairs rejected every iteration.

    Returns:
        IcpResult (transform, final RMS, iterations, converged flag).

    Raises:
        GeometryError: bad shapes, NaN/inf, bad parameters, too few points after trimming.
        DegenerateConfigurationError: collinear/coincident source or target.
    """
    src = check_point_configuration(source, "source")
    tgt = check_point_configuration(target, "target")
    if not 0.0 <= trim_fraction <= 0.9:
        raise GeometryError(f"trim_fraction must be in [0, 0.9], got {trim_fraction}")
    if max_iterations < 1:
        raise GeometryError(f"max_iterations must be >= 1, got {max_iterations}")
    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise GeometryError(f"tolerance_mm must be a positive number, got {tolerance_mm}")
    keep = src.shape[0] - math.floor(trim_fraction * src.shape[0])
    if keep < 3:
        raise GeometryError(f"only {keep} pairs would remain after trimming; need at least 3")
    tree = cKDTree(tgt)
    if isinstance(init, RigidTransform):
        starts = [init]
    elif init == "identity":
        starts = [RigidTransform.identity()]
    elif init == "principal":
        starts = principal_alignment_candidates(src, tgt)
    else:
        raise GeometryError(f"unknown ICP init {init!r}")
    results = [_run(src, tree, tgt, T0, max_iterations, tolerance_mm, keep) for T0 in starts]
    best = min(results, key=lambda r: r.rms_mm)
    return IcpResult(
        best.T_target_from_source, best.rms_mm, best.iterations, best.converged,
        best.inlier_fraction, len(starts),
    )


__all__ = ["IcpResult", "icp", "principal_alignment_candidates", "principal_axes"]
