"""The patient's change since registration, from the skin markers, for a body that may deform.

Every estimator returns a rigid ``T_live_from_ref`` (optical frame) that the control law applies
to the planned path about the entry (:mod:`hil.controller.compensation`): its translation at the
entry is the entry's estimated displacement, its rotation the direction's change. They differ in
what they assume of the body (docs/compensation.md):

- ``rigid`` — Horn's fit of all seen markers (seed 000 section 3, eqs 17-21): exact for a rigid
  body; on a deforming one it averages the motion of markers near and far from the entry.
- ``weighted`` — Horn's fit with each marker weighted by ``exp(-(d / weight_sigma_mm)^2)``, d
  its distance from the entry at registration: the rigid motion of the skin around the entry.
  Assumes the skin moves nearly rigidly within about ``weight_sigma_mm`` of the entry; with few
  markers near the entry its rotation rests on the far ones.
- ``local-tps`` — the weighted fit, then the markers' residual displacements interpolated at the
  entry by a thin-plate spline over the markers' reference plane (Bookstein 1989): the entry's
  own displacement, exact where a marker sits on it. Assumes the skin's displacement is smooth
  between markers; needs 4 seen markers not on a line (else it falls back to ``weighted`` and
  says so), and extrapolates affinely outside their hull.
- ``pattern`` — the entry moved by how the 4D CT shows it moving with the markers
  (hil/controller/entry_pattern.py): the markers' displacements mapped to the entry's through the
  CT's breathing patterns and the linearised rigid motions; the rotation is the weighted fit's.
  Assumes the patient breathes with the CT's patterns; needs the entry at every phase of the
  plan's 4D CT and 4 seen markers that carry the patterns (else it falls back to ``local-tps``,
  then ``weighted``, and says why).

``weighted``'s and ``local-tps``'s per-pair arithmetic after the spline's row (weights, the
weighted fit, the spline's step) is compiled (hil/geometry/_native.c ``local_change``);
:func:`weighted_numpy` and :func:`tps_numpy` are its reference and run when the numpy code is
selected (:mod:`hil.geometry.native`).

Whatever the estimator, the unweighted rigid fit's RMS residual (``rigid_fre_mm``) and per-marker
residuals are reported: the deformation monitor (how far the body is from the rigid copy the
registration assumed).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from hil.controller.entry_pattern import EntryRows
from hil.errors import GeometryError
from hil.geometry import native
from hil.geometry.registration import Registration, register_horn, register_horn_numpy
from hil.geometry.thin_plate import thin_plate_weights
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]
ChangeEstimator = Literal["rigid", "weighted", "local-tps", "pattern"]
CHANGE_ESTIMATORS: tuple[str, ...] = ("rigid", "weighted", "local-tps", "pattern")

#: a marker whose weight is below this share of the largest counts as absent for ``weighted``
_MIN_WEIGHT_SHARE = 1e-3
#: ``local-tps`` needs this many seen markers
TPS_MIN_MARKERS = 4


@dataclass(frozen=True)
class ChangeFit:
    """One pair's estimated change.

    Attributes:
        T_live_from_ref: the change (optical frame) the control law follows.
        estimator: the estimator that produced it (``weighted`` when ``local-tps`` fell back).
        rigid_fre_mm: RMS residual of the unweighted rigid fit (the deformation monitor), mm.
        residuals_mm: per marker (reference order; NaN where not seen) distance of the live marker
            from the rigid fit's prediction, mm.
        markers: markers used.
        fallback: why the configured estimator was not used ("" when it was).
    """

    T_live_from_ref: RigidTransform
    estimator: str
    rigid_fre_mm: float
    residuals_mm: FloatArray
    markers: int
    fallback: str = ""


def _rigid(ref: FloatArray, live: FloatArray) -> Registration | None:
    try:
        return register_horn(live, ref)
    except GeometryError:
        return None


def entry_weights(ref: FloatArray, entry_mm: FloatArray, sigma_mm: float) -> FloatArray:
    """``exp(-(d / sigma)^2)`` of each reference marker's distance d from the entry."""
    d2 = ((ref - entry_mm) ** 2).sum(axis=1)
    out: FloatArray = np.exp(-d2 / (sigma_mm * sigma_mm))
    return out


def weighted_numpy(ref: FloatArray, live: FloatArray, entry_mm: FloatArray,
                   sigma_mm: float) -> RigidTransform | None:
    """``weighted``'s fit in numpy (the reference of the compiled ``local_change``): None with fewer
    than 3 markers keeping a weight or a fit the markers cannot carry."""
    w = entry_weights(ref, entry_mm, sigma_mm)
    keep = w >= _MIN_WEIGHT_SHARE * float(w.max())
    if int(keep.sum()) < 3:
        return None
    try:
        return register_horn_numpy(live[keep], ref[keep], weights=w[keep]).T_fixed_from_moving
    except GeometryError:
        return None


def _plane_coordinates(ref: FloatArray, entry_mm: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The markers and the entry in 2-D coordinates of the markers' best-fit plane."""
    centre = ref.mean(axis=0)
    _, _, vt = np.linalg.svd(ref - centre, full_matrices=False)
    basis = vt[:2].T                                   # (3, 2)
    return (ref - centre) @ basis, ((entry_mm - centre) @ basis)[None, :]


@functools.lru_cache(maxsize=64)
def _tps_row(ref_bytes: bytes, entry_bytes: bytes) -> FloatArray:
    """The spline's interpolation row at the entry for these reference markers (float64 bytes of
    (n, 3) and (3,)), read-only. It depends only on which markers are seen, so a procedure
    computes it once per visible subset (a pair then costs a product, not a solve).

    Raises:
        ValueError: the markers' places cannot carry a spline (not cached: raised every time)."""
    ref = np.frombuffer(ref_bytes, dtype=np.float64).reshape(-1, 3)
    entry = np.frombuffer(entry_bytes, dtype=np.float64)
    xy, entry_xy = _plane_coordinates(ref, entry)
    W = thin_plate_weights(xy, entry_xy)
    W.setflags(write=False)
    return W


def tps_numpy(row: FloatArray, ref: FloatArray, live: FloatArray, base: RigidTransform) -> RigidTransform:
    """``base`` moved so the entry lands where the thin-plate spline of the markers' residual
    displacements (live minus ``base``'s prediction) puts it; ``row`` (n,) the spline's row at the
    entry (:func:`_tps_row`). The numpy reference of ``local_change``'s spline step."""
    delta = row @ (live - base.apply(ref))
    return RigidTransform.from_translation(delta) @ base


def _local(ref: FloatArray, live: FloatArray, entry_mm: FloatArray, sigma_mm: float,
           tps_row: FloatArray | None) -> tuple[RigidTransform, RigidTransform | None] | None:
    """``weighted``'s change and, with the spline's row at the entry, ``local-tps``'s; None when
    ``weighted`` has no fit (fewer than 3 markers near the entry, a degenerate set). Compiled
    (``local_change``) when selected and able, else :func:`weighted_numpy`, :func:`tps_numpy`."""
    k = native.active()
    if k is not None:
        R, t, t_tps = np.empty((3, 3)), np.empty(3), np.empty(3)
        kept = k.local_change(ref, live, np.ascontiguousarray(entry_mm, dtype=np.float64), sigma_mm,
                              _MIN_WEIGHT_SHARE, tps_row, R, t, t_tps)
        if kept == 0:
            return None
        if kept > 0:   # Horn's rotation (a unit quaternion's, eq 16), every value finite: proper
            return (RigidTransform._composed(R, t),
                    None if tps_row is None else RigidTransform._composed(R.copy(), t_tps))
    weighted = weighted_numpy(ref, live, entry_mm, sigma_mm)
    if weighted is None:
        return None
    return weighted, None if tps_row is None else tps_numpy(tps_row, ref, live, weighted)


def estimate_change(reference_mm: FloatArray, live_mm: FloatArray, entry_mm: FloatArray,
                    estimator: ChangeEstimator, weight_sigma_mm: float,
                    pattern: EntryRows | None = None) -> ChangeFit | None:
    """``T_live_from_ref`` from corresponding marker rows (NaN rows = not seen) by ``estimator``
    (module doc), about the entry at registration ``entry_mm`` (optical frame, mm). ``pattern``:
    the ``pattern`` estimator's model for this registration (hil/controller/entry_pattern.py).

    Returns None with fewer than 3 usable, non-degenerate markers (the change is then unknown:
    the controller holds). Never raises for marker geometry: a degenerate layout is a None or a
    fallback named in :attr:`ChangeFit.fallback`.
    """
    ok = np.asarray(np.isfinite(reference_mm).all(axis=1) & np.isfinite(live_mm).all(axis=1), dtype=np.bool_)
    n = int(ok.sum())
    if n < 3:
        return None
    ref = reference_mm[ok].astype(np.float64, copy=False)    # fresh C-contiguous rows
    live = live_mm[ok].astype(np.float64, copy=False)
    rigid = _rigid(ref, live)
    if rigid is None:
        return None
    residuals = np.full(len(reference_mm), math.nan)
    residuals[ok] = rigid.residuals_mm

    def fit(T: RigidTransform, name: str, fallback: str = "") -> ChangeFit:
        return ChangeFit(T, name, float(rigid.fre_rms_mm), residuals, n, fallback)

    if estimator == "rigid":
        return fit(rigid.T_fixed_from_moving, "rigid")
    entry_now, pattern_why = None, ""
    if estimator == "pattern":
        if pattern is None:
            pattern_why = "no breathing pattern for this registration"
        else:
            try:
                entry_now = pattern.entry_mm(ok, ref, live, entry_mm)
            except ValueError as exc:
                pattern_why = f"breathing pattern: {exc}"
    tps_row, tps_why = None, ""
    if estimator == "local-tps" or (estimator == "pattern" and entry_now is None):
        tps_row, tps_why = _spline_row(ref, entry_mm)
    local = _local(ref, live, entry_mm, weight_sigma_mm, tps_row)
    if local is None:
        return fit(rigid.T_fixed_from_moving, "rigid",
                   "fewer than 3 markers near the entry: the rigid change of all")
    weighted, tps = local
    if estimator == "weighted":
        return fit(weighted, "weighted")
    if entry_now is not None:   # the entry where the patterns put it, the weighted fit's rotation
        # translation(entry_now - weighted(entry)) @ weighted, composed directly: the parts of a
        # valid transform and a finite shift (the checked constructor's cost, on the pair path)
        R, t = weighted.R, weighted.t
        moved = RigidTransform._composed(R.copy(), t + (entry_now - (R @ entry_mm + t)))
        return fit(moved, "pattern")
    if tps is None:
        return fit(weighted, "weighted", "; ".join(w for w in (pattern_why, tps_why) if w))
    return fit(tps, "local-tps", pattern_why)


def _spline_row(ref: FloatArray, entry_mm: FloatArray) -> tuple[FloatArray | None, str]:
    """``local-tps``'s row at the entry for the seen reference markers, or None and why not."""
    if len(ref) < TPS_MIN_MARKERS:
        return None, f"{len(ref)} markers seen: the local spline needs {TPS_MIN_MARKERS}"
    try:
        return _tps_row(ref.tobytes(), np.ascontiguousarray(entry_mm, dtype=np.float64).tobytes())[0], ""
    except ValueError as exc:
        return None, f"local spline: {exc}"
