"""The ``pattern`` change estimator's model: the entry's displacement from the skin markers' by the
breathing patterns of the planning 4D CT.

Why (issue 41 point 1): ``local-tps`` interpolates the markers' displacements at the entry with a
spline over markers tens of mm apart; where the skin's displacement varies over shorter distances
(amplitude and direction change across the skin, thoracic and abdominal breathing blend) the
spline misses it. On the simulated patient with the markers' true positions, the spline leaves
the entry p50 / p95 0.29 / 2.60 mm off over free breathing (seeds 1-12, 55 s each); this model
0.12 / 0.62 mm (``tools/bench entry``; docs/benchmarks.md, tenth session). A 4D CT shows the
skin at every phase, the entry with it: how the entry moves with the markers is then measured, not
interpolated.

**The model** (fitted once from the plan's ``phases`` that give ``entry_mm``,
hil/controller/plan_file.py). With ``F_0``, ``e_0`` the registered phase (end-exhale) and ``F_k``,
``e_k`` phase k (image frame):

- ``D_k = vec(F_k - F_0)`` (3N) and ``E_k = e_k - e_0`` (3);
- the skin's breathing patterns ``U`` (3N x r): the first right singular vectors of the stacked
  ``D_k``, at most :data:`MAX_PATTERNS`; one whose singular value is under :data:`PATTERN_SHARE`
  of the first is left out (the CT's localisation noise, not breathing);
- the entry per unit score ``C = argmin sum_k |E_k - C z_k|^2 + lambda |C_2|^2`` (3 x r),
  ``z_k = U^T D_k`` (least squares through the registered phase), with a ridge ``lambda`` on the
  coefficients of the patterns after the first (``C_2``), chosen from :data:`RIDGE_GRID_MM2` by
  leave-one-out over the phases (PRESS, in closed form: ``sum_k |r_k / (1 - H_kk)|^2``, ``r_k``
  the fit's residual at phase k and ``H`` its hat matrix; 0 when that fits best). Why: the second
  pattern is the smaller, and its scores over a CT's few inhaling phases are small, so the CT's
  localisation error passes into its coefficient amplified. Offline, with the markers' true
  positions (seeds 1-12, 0.3 mm CT; docs/benchmarks.md, twelfth session) the entry's p95 went
  0.62 -> 0.55 mm; with an exact CT the ridge is 0 and the model exact.

**Live** (:meth:`EntryPattern.registered`, optical frame after a registration ``R``, ``t``): the
markers' basis ``B`` (3N x (r + 6)) holds the patterns turned into the optical frame and the six
linearised rigid motions about the entry (a translation; a rotation ``w``, displacing a point
``x`` by ``w x (x - e)``); the entry's ``B_e`` (3 x (r + 6)) the entry per score and the same
rigid motions at the entry (``w x 0 = 0``). For the seen markers, ``B[seen]^+``
(:meth:`EntryRows.solver`, once per set of seen markers) gives the parameters ``p`` of any marker
displacement the model spans (breathing by the 4D CT's patterns at any depth, a small rigid
motion), and ``B_e p`` the entry's displacement.

Each pair (:func:`hil.controller.change_estimate.estimate_change`, :meth:`EntryRows.entry_mm`):
the scores and the rigid motion ``M`` by least squares, ``B[seen]^+ (live - ref)``; then again
with the live markers pulled back by ``M`` (a turn since registration also turns the breathing
displacement, a cross term the linear basis does not hold); the entry at ``M(e_0 + B_e p)``. The
change is the ``weighted`` fit moved so the entry lands there (its rotation, so the path's
direction before a target model, is the weighted fit's). Breathing by the patterns is followed
exactly; of a rigid turn since registration little is left (on the test body breathing 8 and 5 mm
deep, 0.006 mm for 2 deg: tests/controller/test_entry_pattern.py).

**What it assumes, where it fails**: the patient breathes with the 4D CT's patterns (the depth
and the mix of the patterns are free; a new pattern is not); the CT's skin surface gives the
entry at every phase; a rigid motion since registration of a few degrees at most (the solve
linearises it about the first one). A pair whose markers the model leaves more than
``pattern_residual_mm`` off (per-marker RMS: a cough, breathing unlike at the CT, a marker swapped)
falls back and says by how much. It needs :data:`MIN_MARKERS` seen markers whose basis is well
conditioned (:data:`MIN_CONDITION`); else the pair falls back to ``local-tps`` (then
``weighted``) and says why. The CT's localisation error passes into ``C``.

Cost per pair: the ``weighted`` fit and the entry's arithmetic, both compiled
(hil/geometry/_native.c ``local_change``, ``pattern_entry``; :func:`entry_numpy` is the reference
it is tested against and what runs when the numpy code is selected, :mod:`hil.geometry.native`);
the solve runs once per set of seen markers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hil.controller.plan_file import ProcedurePlan
from hil.errors import InputFileError
from hil.geometry import native
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]

__all__ = ["MAX_PATTERNS", "MIN_CONDITION", "MIN_MARKERS", "PATTERN_SHARE", "RIDGE_GRID_MM2", "EntryPattern",
           "EntryRows", "Solver", "cross_matrices", "entry_coefficients", "entry_numpy", "fit_entry_pattern"]

#: the most breathing patterns the model keeps (thoracic and abdominal breathing)
MAX_PATTERNS = 2
#: a pattern whose singular value is under this share of the first is left out
PATTERN_SHARE = 0.1
#: the model needs at least this many phases besides the registered one
MIN_PHASES = 2
#: the fewest seen markers the rows are solved for
MIN_MARKERS = 4
#: the seen markers' basis (columns scaled to unit length) must have its smallest singular value at
#: least this share of its largest
MIN_CONDITION = 1e-3
#: the ridge weights tried on the entry's coefficients of the patterns after the first, mm^2 of
#: score (module doc)
RIDGE_GRID_MM2: tuple[float, ...] = (0.0, *(float(x) for x in np.logspace(-1.0, 4.0, 26)))
#: the row matrices kept, one per set of seen markers
_ROWS_KEPT = 64


@dataclass(frozen=True)
class EntryPattern:
    """The model in the image frame (module doc).

    Attributes:
        patterns: ``U``, (N, 3, r): the skin's breathing patterns, per marker (unit over all).
        entry_per_score: ``C``, (3, r): the entry's displacement per mm of each pattern's score.
        explained: the share of the fiducials' displacement variance the patterns hold.
        fit_residual_mm: the RMS of the entry's displacement the model leaves over the phases.
        ridge_mm2: the ridge the leave-one-out chose (module doc), mm^2.
    """

    patterns: FloatArray
    entry_per_score: FloatArray
    explained: float
    fit_residual_mm: float
    ridge_mm2: float = 0.0

    def registered(self, T_optical_from_image: RigidTransform, reference_optical_mm: FloatArray,
                   entry_optical_mm: FloatArray, residual_bound_mm: float = 2.0) -> EntryRows:
        """The model's rows for one registration (optical frame; the reference markers in the
        plan's order, the entry at registration; the residual bound of :meth:`EntryRows.entry_mm`,
        mm)."""
        R = T_optical_from_image.R
        n = len(reference_optical_mm)
        turned = np.einsum("ij,njr->nir", R, self.patterns)                  # (N, 3, r)
        rigid = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)),
                                cross_matrices(reference_optical_mm - entry_optical_mm)], axis=2)
        basis = np.concatenate([turned, rigid], axis=2)                          # (N, 3, r + 6)
        r = self.patterns.shape[2]
        at_entry = np.zeros((3, r + 6))
        at_entry[:, :r] = R @ self.entry_per_score
        at_entry[:, r:r + 3] = np.eye(3)
        return EntryRows(basis, at_entry, residual_bound_mm)


def cross_matrices(d: FloatArray) -> FloatArray:
    """``M_i`` with ``M_i @ w = w x d_i``, (n, 3, 3)."""
    out = np.zeros((len(d), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = d[:, 2], -d[:, 1]
    out[:, 1, 0], out[:, 1, 2] = -d[:, 2], d[:, 0]
    out[:, 2, 0], out[:, 2, 1] = d[:, 1], -d[:, 0]
    return out


@dataclass
class EntryRows:
    """The model for one registration (module doc): ``basis`` (N, 3, r + 6) per marker, ``at_entry``
    (3, r + 6); :meth:`solver` solves and keeps the pseudo-inverse of a set of seen markers."""

    basis: FloatArray
    at_entry: FloatArray
    #: a pair whose markers the model leaves more than this off (per-marker RMS, mm) is refused
    residual_bound_mm: float = 2.0
    _rows: dict[bytes, Solver | str] = field(default_factory=dict, repr=False)

    def solver(self, seen: NDArray[np.bool_]) -> Solver:
        """The :class:`Solver` of the seen markers (``seen``: (N,) mask in the plan's order), solved
        once per set and kept.

        Raises:
            ValueError: fewer than :data:`MIN_MARKERS` seen, or a basis they cannot carry (the
                reason; raised every time for that set).
        """
        key = np.asarray(seen, dtype=np.bool_).tobytes()
        got = self._rows.get(key)
        if got is None:
            got = self._solve(np.asarray(seen, dtype=np.bool_))
            if len(self._rows) >= _ROWS_KEPT:
                self._rows.clear()
            self._rows[key] = got
        if isinstance(got, str):
            raise ValueError(got)
        return got

    def entry_mm(self, seen: NDArray[np.bool_], reference_mm: FloatArray, live_mm: FloatArray,
                 entry_mm: FloatArray) -> FloatArray:
        """Where the model puts the entry (optical, mm) for the seen markers' reference and live
        positions (n, 3) and the entry at registration (module doc): the linear solve, then once
        more with the live markers pulled back by the rigid motion it found, so that a turn since
        registration does not mix with the breathing (the cross term of the first solve). Compiled
        (``pattern_entry``) when selected and able, else :func:`entry_numpy`.

        Raises:
            ValueError: as :meth:`solver`; an entry that is not finite; or the markers the model
                leaves more than ``residual_bound_mm`` off (per-marker RMS after the second solve:
                a cough, a new way of breathing, a marker swapped), saying by how much.
        """
        sol = self.solver(seen)
        k = native.active()
        out = np.empty(4)
        if k is None or k.pattern_entry(sol.P6, sol.E, sol.Q, reference_mm, live_mm,
                                        np.ascontiguousarray(entry_mm, dtype=np.float64), out) != 0:
            out = entry_numpy(sol, reference_mm, live_mm, entry_mm)
        x, y, z, resid_mm = out.tolist()
        if not math.isfinite(x + y + z):   # the caller composes it unchecked
            raise ValueError("the breathing patterns put the entry at a value that is not finite")
        if not resid_mm <= self.residual_bound_mm:
            raise ValueError(f"the markers do not move as the 4D CT's breathing patterns (per-marker RMS "
                             f"residual {resid_mm:.2f} mm beyond {self.residual_bound_mm} mm)")
        return out[:3]

    def _solve(self, seen: NDArray[np.bool_]) -> Solver | str:
        n = int(seen.sum())
        if n < MIN_MARKERS:
            return f"{n} markers seen: the breathing pattern needs {MIN_MARKERS}"
        B = self.basis[seen].reshape(3 * n, -1)
        scale = np.linalg.norm(B, axis=0)
        if not (scale > 0.0).all():
            return "the seen markers do not show every breathing pattern"
        sv = np.linalg.svd(B / scale, compute_uv=False)
        if not sv[-1] >= MIN_CONDITION * sv[0]:
            return (f"the seen markers cannot tell the breathing patterns from a rigid motion "
                    f"(condition {sv[0] / max(float(sv[-1]), 1e-300):.0f})")
        P = np.asarray(np.linalg.pinv(B), dtype=np.float64)
        r = P.shape[0] - 6
        return Solver(P6=_frozen(P[r:]), E=_frozen(self.at_entry @ P), Q=_frozen(np.eye(3 * n) - B @ P))


@dataclass(frozen=True)
class Solver:
    """One set of seen markers' solve (read-only, C-contiguous; n seen markers): ``P6`` (6, 3n) the
    rows of ``B[seen]^+`` that give the translation and the rotation vector; ``E`` (3, 3n) the
    entry's displacement ``B_e B[seen]^+``; ``Q`` (3n, 3n) what the model leaves, ``I - B B^+``."""

    P6: FloatArray
    E: FloatArray
    Q: FloatArray


def _frozen(a: FloatArray) -> FloatArray:
    out = np.ascontiguousarray(a, dtype=np.float64)
    out.setflags(write=False)
    return out


def entry_numpy(sol: Solver, reference_mm: FloatArray, live_mm: FloatArray,
                entry_mm: FloatArray) -> FloatArray:
    """:meth:`EntryRows.entry_mm`'s arithmetic in numpy (the reference of the compiled
    ``pattern_entry``): (4,) the entry (optical, mm) and the per-marker RMS residual (mm)."""
    p6 = sol.P6 @ (live_mm - reference_mm).reshape(-1)
    R = rotvec_to_matrix(p6[3:6])
    shift = p6[:3]
    moved = ((live_mm - entry_mm - shift) @ R + entry_mm - reference_mm).reshape(-1)   # R^T (.) per row
    unexplained = sol.Q @ moved
    out = np.empty(4)
    out[:3] = R @ (sol.E @ moved) + entry_mm + shift
    out[3] = np.sqrt(unexplained @ unexplained / len(reference_mm))
    return out


def fit_entry_pattern(plan: ProcedurePlan) -> EntryPattern:
    """Fit the model to ``plan.phases`` (module doc).

    Raises:
        InputFileError: naming the plan: fewer than 2 phases, phases without ``entry_mm``, or
            fiducials that do not move over them.
    """
    phases = plan.phases
    if len(phases) < MIN_PHASES:
        raise InputFileError(plan.source, f"the pattern estimator needs a 4D CT: >= {MIN_PHASES} breathing "
                             f"phases in the plan's 'phases', it has {len(phases)}")
    entries = [ph.entry_mm for ph in phases]
    if any(e is None for e in entries):
        raise InputFileError(plan.source, "the pattern estimator needs the entry at every phase of the 4D "
                             "CT ('entry_mm' in each of the plan's 'phases')")
    D = np.stack([(ph.fiducials_mm - plan.fiducials_mm).reshape(-1) for ph in phases])
    E = np.stack([np.asarray(e, dtype=np.float64) - plan.entry_mm for e in entries if e is not None])
    _, sv, vt = np.linalg.svd(D, full_matrices=False)
    if not float(sv[0]) > 0.0:
        raise InputFileError(plan.source, "phases: the fiducials do not move over the 4D CT: no breathing "
                             "pattern to correlate the entry with")
    r = int(min(MAX_PATTERNS, int((sv >= PATTERN_SHARE * sv[0]).sum())))
    U = vt[:r].T                                   # (3N, r)
    Z = D @ U                                      # (K, r)
    coef, ridge = entry_coefficients(Z, E)        # (r, 3)
    resid = float(np.sqrt(((E - Z @ coef) ** 2).sum(axis=1).mean()))
    return EntryPattern(patterns=U.reshape(-1, 3, r), entry_per_score=np.ascontiguousarray(coef.T),
                        explained=float((sv[:r] ** 2).sum() / (sv**2).sum()), fit_residual_mm=resid,
                        ridge_mm2=ridge)


def entry_coefficients(Z: FloatArray, E: FloatArray) -> tuple[FloatArray, float]:
    """(``C^T`` (r, 3), the ridge) of the module doc: the ridge on the patterns after the first
    with the least leave-one-out error over the phases. A ridge at which some phase has all the
    leverage (``H_kk`` = 1: its left-out error is not defined) is not chosen."""
    r = Z.shape[1]
    penalty = np.eye(r)
    penalty[0, 0] = 0.0
    best: tuple[float, FloatArray, float] | None = None
    for ridge in RIDGE_GRID_MM2 if r > 1 else (0.0,):
        A = Z.T @ Z + ridge * penalty
        try:
            coef = np.asarray(np.linalg.solve(A, Z.T @ E), dtype=np.float64)
            H_diag = np.einsum("kr,rk->k", Z, np.linalg.solve(A, Z.T))
        except np.linalg.LinAlgError:
            continue
        left = 1.0 - H_diag
        if not (left > 1e-9).all():
            continue
        press = float((((E - Z @ coef) / left[:, None]) ** 2).sum())
        if best is None or press < best[0]:
            best = (press, coef, ridge)
    if best is None:          # every phase's leverage 1 (as many phases as unknowns): plain fit
        return np.asarray(np.linalg.lstsq(Z, E, rcond=None)[0], dtype=np.float64), 0.0
    return best[1], best[2]
