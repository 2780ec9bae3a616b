"""Correspondence-free matching of a small marker set (model, e.g. CT markers) to measured points.

A camera does not see markers in CT order, may miss some and may report spurious blobs. The
matcher finds which measured point is which model marker using only rigid-body invariants:

1. Signatures: the pairwise distance matrices of the model and the measurement. A model triangle
   ``(i, j, k)`` can only correspond to a measured triangle ``(a, b, c)`` whose three side lengths
   agree within ``2 * tolerance_mm`` (exhaustive over triangles; the sets are small).
2. Hypotheses: each compatible, non-degenerate triangle pair fixes a rigid transform (SVD); the
   whole model is mapped and assigned to measured points one-to-one (Hungarian assignment on
   distances, pairs farther than ``tolerance_mm`` rejected); the transform is refined on all
   matched pairs and the assignment redone once (consistency check).
3. Choice: the hypothesis with the most matched markers wins, ties broken by the lowest RMS.
   A model marker the others place more than ``tolerance_mm`` from every measured point is
   *excluded* (e.g. a marker that slid on the skin) and reported; unassigned measured points are
   *spurious*.
4. Ambiguity: when a *different* assignment matches as many markers with an RMS within
   ``ambiguity_margin_mm`` of the best (a near-symmetric layout), the result is flagged
   ``ambiguous=True`` (and, with ``strict=True``, :class:`AmbiguousMatchError` is raised) rather
   than silently picking one.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from hil.errors import AmbiguousMatchError, DegenerateConfigurationError, GeometryError
from hil.geometry.registration import check_point_configuration, register_svd
from hil.geometry.transform import RigidTransform, as_points

FloatArray = NDArray[np.float64]

#: Hard cap on evaluated hypotheses (bounds run time for large or highly symmetric sets).
MAX_HYPOTHESES = 20000


@dataclass(frozen=True)
class MarkerMatch:
    """Result of :func:`match_markers`.

    Attributes:
        model_to_measured: model index -> measured index, for every matched marker.
        T_measured_from_model: rigid transform fitted on the matched pairs.
        residuals_mm: model index -> ``|T model_i - measured_j|`` for matched markers.
        excluded_model: model markers not matched (missing or outliers), ascending.
        spurious_measured: measured points not assigned to any marker, ascending.
        ambiguous: another assignment explains the data about as well (near-symmetric layout).
        fre_rms_mm: RMS of the matched residuals.
        alternatives: the competing assignments that made the match ambiguous (empty otherwise).
        excluded_distance_mm: excluded model index -> distance from where the fit puts it to the
            nearest measured point (how far an outlier marker moved, or that it is missing).
    """

    model_to_measured: dict[int, int]
    T_measured_from_model: RigidTransform
    residuals_mm: dict[int, float]
    excluded_model: tuple[int, ...]
    spurious_measured: tuple[int, ...]
    ambiguous: bool
    fre_rms_mm: float
    alternatives: tuple[dict[int, int], ...] = ()
    excluded_distance_mm: dict[int, float] = field(default_factory=dict)


@dataclass(frozen=True)
class _Hypothesis:
    pairs: tuple[tuple[int, int], ...]  # sorted (model, measured)
    T: RigidTransform
    rms_mm: float


def _assign(
    model: FloatArray, measured: FloatArray, T: RigidTransform, tolerance_mm: float
) -> list[tuple[int, int]]:
    D = cdist(T.apply(model), measured)
    big = 1e6 + float(D.max())
    cost = np.where(tolerance_mm >= D, D, big)
    rows, cols = linear_sum_assignment(cost)
    return sorted((int(r), int(c)) for r, c in zip(rows, cols, strict=True) if D[r, c] <= tolerance_mm)


def _fit(
    model: FloatArray, measured: FloatArray, pairs: list[tuple[int, int]]
) -> tuple[RigidTransform, float] | None:
    mi = [p[0] for p in pairs]
    me = [p[1] for p in pairs]
    try:
        reg = register_svd(measured[me], model[mi])
    except DegenerateConfigurationError:
        return None
    return reg.T_fixed_from_moving, reg.fre_rms_mm


def match_markers(
    measured_mm: ArrayLike,
    model_mm: ArrayLike,
    *,
    tolerance_mm: float = 2.0,
    min_matched: int = 3,
    ambiguity_margin_mm: float | None = None,
    strict: bool = False,
) -> MarkerMatch:
    """Find which measured point is which model marker, without known correspondences.

    Args:
        measured_mm: (M, 3) measured marker centres (e.g. optical frame), mm, any order.
        model_mm: (N, 3) the marker layout (e.g. CT frame), mm.
        tolerance_mm: largest accepted distance between a mapped model marker and its measured
            point; also sets the signature tolerance (``2 * tolerance_mm`` on distances).
        min_matched: fewest markers a valid match must contain (>= 3).
        ambiguity_margin_mm: RMS margin within which a different assignment counts as equally
            good (default ``tolerance_mm / 2``).
        strict: raise :class:`AmbiguousMatchError` instead of returning an ambiguous match.

    Returns:
        MarkerMatch (see class docs).

    Raises:
        GeometryError: bad shapes, NaN/inf, bad parameters, or no consistent match of at least
            ``min_matched`` markers.
        DegenerateConfigurationError: the model markers are collinear or coincident.
        AmbiguousMatchError: ``strict=True`` and the match is ambiguous.
    """
    measured = as_points(measured_mm, "measured")
    model = check_point_configuration(model_mm, "model")
    margin = _check_match_parameters(tolerance_mm, min_matched, ambiguity_margin_mm, measured.shape[0])
    hypotheses = _collect_hypotheses(model, measured, tolerance_mm)
    valid = _valid_hypotheses_best_first(hypotheses, min_matched, tolerance_mm)
    best = valid[0]
    rivals = _rival_assignments(valid, margin)
    ambiguous = bool(rivals)
    if ambiguous and strict:
        raise AmbiguousMatchError(
            f"{len(rivals) + 1} assignments of {len(best.pairs)} markers fit within {margin} mm RMS "
            "of each other; the marker layout is too symmetric to tell them apart"
        )
    return _marker_match(model, measured, best, ambiguous, rivals)


def _check_match_parameters(
    tolerance_mm: float, min_matched: int, ambiguity_margin_mm: float | None, n_measured: int
) -> float:
    """Validate :func:`match_markers`' parameters; return the ambiguity margin (mm RMS).

    Raises:
        GeometryError: non-positive/non-finite tolerance, ``min_matched < 3`` or fewer than
            ``min_matched`` measured points.
    """
    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise GeometryError(f"tolerance_mm must be a positive number, got {tolerance_mm}")
    if min_matched < 3:
        raise GeometryError(f"min_matched must be at least 3, got {min_matched}")
    margin = tolerance_mm / 2.0 if ambiguity_margin_mm is None else float(ambiguity_margin_mm)
    if n_measured < min_matched:
        raise GeometryError(
            f"{n_measured} measured point(s), fewer than the {min_matched} needed for a match"
        )
    return margin


def _collect_hypotheses(
    model: FloatArray, measured: FloatArray, tolerance_mm: float
) -> dict[tuple[tuple[int, int], ...], _Hypothesis]:
    """Steps 1-2 of the module docs: every distinct assignment that a compatible triangle pair leads to.

    Model triangles with a side shorter than ``2 * tolerance_mm`` are skipped (they cannot fix a
    rotation reliably); at most :data:`MAX_HYPOTHESES` triangle pairs are evaluated. Keys are the
    sorted (model, measured) pairs, in discovery order.
    """
    n, m = model.shape[0], measured.shape[0]
    Dn = cdist(model, model)
    Dm = cdist(measured, measured)
    sig_tol = 2.0 * tolerance_mm
    min_side = sig_tol  # a triangle with a shorter side cannot fix a rotation reliably
    hypotheses: dict[tuple[tuple[int, int], ...], _Hypothesis] = {}
    evaluated = 0
    distinct = ~np.eye(m, dtype=bool)
    for i, j, k in itertools.combinations(range(n), 3):
        sides = (Dn[i, j], Dn[j, k], Dn[i, k])
        if min(sides) < min_side:
            continue
        ok_ij = (np.abs(Dm - Dn[i, j]) <= sig_tol) & distinct
        ok_jk = (np.abs(Dm - Dn[j, k]) <= sig_tol) & distinct
        ok_ik = (np.abs(Dm - Dn[i, k]) <= sig_tol) & distinct
        cand = ok_ij[:, :, None] & ok_jk[None, :, :] & ok_ik[:, None, :]
        for a, b, c in zip(*np.nonzero(cand), strict=True):
            evaluated += 1
            if evaluated > MAX_HYPOTHESES:
                break
            triangle = [(i, int(a)), (j, int(b)), (k, int(c))]
            _add_hypothesis(model, measured, triangle, tolerance_mm, hypotheses)
        if evaluated > MAX_HYPOTHESES:
            break
    return hypotheses


def _add_hypothesis(
    model: FloatArray,
    measured: FloatArray,
    triangle: list[tuple[int, int]],
    tolerance_mm: float,
    hypotheses: dict[tuple[tuple[int, int], ...], _Hypothesis],
) -> None:
    """Grow one triangle correspondence into a whole assignment and record it in ``hypotheses``.

    The triangle fixes a transform, the whole model is assigned within ``tolerance_mm``, refitted
    on all pairs and assigned once more (step 2 of the module docs). Nothing is recorded when a fit
    is degenerate, fewer than 3 markers match, or the first assignment was already seen.
    """
    seed = _fit(model, measured, triangle)
    if seed is None:
        return
    pairs = _assign(model, measured, seed[0], tolerance_mm)
    if len(pairs) < 3:
        return
    key = tuple(pairs)
    if key in hypotheses:
        return
    refined = _fit(model, measured, pairs)
    if refined is None:
        return
    pairs2 = _assign(model, measured, refined[0], tolerance_mm)
    if pairs2 != pairs:
        refit = _fit(model, measured, pairs2) if len(pairs2) >= 3 else None
        if refit is None:
            return
        pairs, refined = pairs2, refit
        key = tuple(pairs)
    hypotheses[key] = _Hypothesis(key, refined[0], refined[1])


def _valid_hypotheses_best_first(
    hypotheses: dict[tuple[tuple[int, int], ...], _Hypothesis], min_matched: int, tolerance_mm: float
) -> list[_Hypothesis]:
    """Hypotheses with at least ``min_matched`` markers, most markers then lowest RMS first (step 3).

    Raises:
        GeometryError: no hypothesis matches ``min_matched`` markers.
    """
    valid = [h for h in hypotheses.values() if len(h.pairs) >= min_matched]
    if not valid:
        best_count = max((len(h.pairs) for h in hypotheses.values()), default=0)
        raise GeometryError(
            f"no consistent match of at least {min_matched} markers within {tolerance_mm} mm "
            f"(best found: {best_count})"
        )
    valid.sort(key=lambda h: (-len(h.pairs), h.rms_mm))
    return valid


def _rival_assignments(valid: list[_Hypothesis], margin: float) -> tuple[dict[int, int], ...]:
    """Other assignments as large as the best (``valid[0]``) with an RMS within ``margin`` mm (step 4)."""
    best = valid[0]
    best_map = dict(best.pairs)
    return tuple(
        dict(h.pairs) for h in valid[1:]
        if len(h.pairs) == len(best.pairs) and h.rms_mm <= best.rms_mm + margin and dict(h.pairs) != best_map
    )


def _marker_match(
    model: FloatArray,
    measured: FloatArray,
    best: _Hypothesis,
    ambiguous: bool,
    rivals: tuple[dict[int, int], ...],
) -> MarkerMatch:
    """The :class:`MarkerMatch` of the chosen hypothesis: residuals, excluded and spurious points (mm)."""
    n, m = model.shape[0], measured.shape[0]
    best_map = dict(best.pairs)
    mapped = best.T.apply(model)
    residuals = {mi: float(np.linalg.norm(mapped[mi] - measured[me])) for mi, me in best.pairs}
    excluded = tuple(i for i in range(n) if i not in best_map)
    nearest = cdist(mapped[list(excluded)], measured).min(axis=1) if excluded else np.zeros(0)
    excluded_distance = {i: float(d) for i, d in zip(excluded, nearest, strict=True)}
    used = set(best_map.values())
    spurious = tuple(j for j in range(m) if j not in used)
    return MarkerMatch(
        model_to_measured=best_map,
        T_measured_from_model=best.T,
        residuals_mm=residuals,
        excluded_model=excluded,
        spurious_measured=spurious,
        ambiguous=ambiguous,
        fre_rms_mm=best.rms_mm,
        alternatives=rivals,
        excluded_distance_mm=excluded_distance,
    )
