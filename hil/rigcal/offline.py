"""Hand-eye calibration from recorded pose pairs, both set-ups (issue 43; docs/rig-calibration.md).

Conventions (kept exactly; ``B_k = T_base_from_flange``, ``C_k = T_camera_from_target``, mm):

* eye-to-hand (camera fixed, target on the flange): ``C_k = Z @ B_k @ X`` with
  ``X = T_flange_from_target`` and ``Z = T_camera_from_base`` (AX = ZB, robot-world/hand-eye);
* eye-in-hand (camera on the flange, target fixed): ``T_base_from_target = B_k @ X @ C_k`` with
  ``X = T_flange_from_camera`` and ``Z = T_base_from_target`` (AX = XB).

1. Closed forms through OpenCV: ``calibrateHandEye`` (Tsai-Lenz 1989, Park-Martin 1994,
   Horaud-Dornaika 1995, Andreff 1999, Daniilidis 1999), which solves the eye-in-hand model
   ``gripper2base @ cam2gripper @ target2cam = const``: eye-in-hand passes ``B_k``, ``C_k`` and
   gets ``X``; eye-to-hand passes ``B_k^-1``, ``C_k`` and gets ``Z^-1`` (OpenCV's documented
   eye-to-hand use). The other unknown is the chordal mean of its per-pair values.
   ``calibrateRobotWorldHandEye`` (Shah 2013, Li 2010) solves ``world2cam @ base2world =
   gripper2cam @ base2gripper``: eye-to-hand passes ``C_k``, ``B_k`` and gets ``X^-1``, ``Z``;
   eye-in-hand passes ``B_k^-1``, ``C_k`` and gets ``Z``, ``X``.
2. Refinement: both unknowns jointly by scipy ``least_squares`` (soft-L1 loss) on every pair's
   translation error (mm) and rotation error (rotation vector, deg), each divided by the start's
   median error of its kind, from the closed form that fits best.
3. Outliers: a pair whose normalised error is beyond ``median + outlier_mads * 1.4826 * MAD`` is
   dropped and the fit repeated (never more than ``max_outlier_fraction`` of the pairs); dropped
   pairs are named.
4. Validation: every ``holdout_every``-th pair (file/time order) is never fitted; the model's RMS
   errors on them are reported.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from hil.rigcal.samples import FloatArray, PosePairs, SamplesError, check_motion, inverse, transform

SETUPS = ("eye-to-hand", "eye-in-hand")
HAND_EYE_METHODS = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")
ROBOT_WORLD_METHODS = ("SHAH", "LI")
#: rounds of outlier rejection (each drops every pair beyond the threshold, then refits)
MAX_REJECTION_ROUNDS = 6


@dataclass(frozen=True)
class OfflineSettings:
    """Knobs of :func:`solve_offline`.

    Attributes:
        max_pairs: at most this many pairs are used, evenly spread over the file (time) order.
        holdout_every: every n-th of them is held out for validation (0: none).
        outlier_mads: rejection threshold, robust standard deviations above the median.
        max_outlier_fraction: never reject more than this share of the fitted pairs.
    """

    max_pairs: int = 100
    holdout_every: int = 5
    outlier_mads: float = 4.0
    max_outlier_fraction: float = 0.25


@dataclass(frozen=True)
class PairError:
    """One pair's fit: ``where`` in the file, errors in mm and deg, ``role`` used / outlier /
    held_out."""

    where: str
    error_mm: float
    error_deg: float
    role: str


@dataclass(frozen=True)
class OfflineResult:
    """A hand-eye calibration from recorded pairs (module doc for X and Z)."""

    setup: str
    X: FloatArray
    Z: FloatArray
    pairs: int
    per_pair: tuple[PairError, ...]
    residual_mm_rms: float
    residual_deg_rms: float
    validation: dict[str, Any]
    methods: dict[str, dict[str, Any]]
    start: str
    solve_s: float

    @property
    def outliers(self) -> list[str]:
        return [p.where for p in self.per_pair if p.role == "outlier"]

    @property
    def pairs_used(self) -> int:
        return sum(p.role == "used" for p in self.per_pair)


def _chordal_mean(T: FloatArray) -> FloatArray:
    """Mean of rigid transforms (N, 4, 4): the rotation nearest the summed rotations (chordal L2
    mean, Hartley et al. 2013 sec. 5.3), the mean translation."""
    u, _, vt = np.linalg.svd(T[:, :3, :3].sum(axis=0))
    R = u @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)))]) @ vt
    return transform(R, T[:, :3, 3].mean(axis=0))


class ClosedFormError(ValueError):
    """A closed form returned something that is not a rigid transform (NaN, a reflection)."""


def _cv_pose(R: Any, t: Any) -> FloatArray:
    """The 4x4 of an OpenCV result, its rotation projected on SO(3) (:func:`_proper`).

    Raises:
        ClosedFormError: not a rigid transform.
    """
    T = _proper(transform(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).reshape(3)))
    if T is None:
        raise ClosedFormError("its result is not a rotation (data that method cannot solve)")
    return T


def _split(T: FloatArray) -> tuple[list[FloatArray], list[FloatArray]]:
    return [m[:3, :3].copy() for m in T], [m[:3, 3].reshape(3, 1).copy() for m in T]


def closed_form(method: str, B: FloatArray, C: FloatArray,
                eye_in_hand: bool) -> tuple[FloatArray, FloatArray]:
    """``(X, Z)`` of one OpenCV closed form (module doc, step 1).

    Raises:
        cv2.error: OpenCV refused the data.
        ClosedFormError: OpenCV returned NaN or a non-rotation.
    """
    import cv2  # imported lazily, as elsewhere in the core

    if method in HAND_EYE_METHODS:
        Rg, tg = _split(B if eye_in_hand else inverse(B))
        Rc, tc = _split(C)
        R, t = cv2.calibrateHandEye(Rg, tg, Rc, tc, method=getattr(cv2, f"CALIB_HAND_EYE_{method}"))
        M = _cv_pose(R, t)
        if eye_in_hand:
            return M, _chordal_mean(B @ M @ C)
        Z = inverse(M)
        return _chordal_mean(inverse(Z @ B) @ C), Z
    if eye_in_hand:
        Rw, tw = _split(inverse(B))
        Rb, tb = _split(C)
    else:
        Rw, tw = _split(C)
        Rb, tb = _split(B)
    flag = getattr(cv2, f"CALIB_ROBOT_WORLD_HAND_EYE_{method}")
    Rbw, tbw, Rgc, tgc = cv2.calibrateRobotWorldHandEye(Rw, tw, Rb, tb, method=flag)
    base2world, gripper2cam = _cv_pose(Rbw, tbw), _cv_pose(Rgc, tgc)
    if eye_in_hand:
        return gripper2cam, base2world
    return inverse(base2world), gripper2cam


def pair_errors(X: FloatArray, Z: FloatArray, B: FloatArray, C: FloatArray,
                eye_in_hand: bool) -> tuple[FloatArray, FloatArray]:
    """Per pair ``(translation error (N, 3) mm, rotation error (N, 3) rotation vector deg)``:
    eye-to-hand, ``Z B_k X`` against ``C_k`` (camera frame); eye-in-hand, ``B_k X C_k`` against
    ``Z`` (base frame)."""
    if eye_in_hand:
        pred, meas = B @ X @ C, np.broadcast_to(Z, B.shape)
    else:
        pred, meas = Z @ B @ X, C
    dt = pred[:, :3, 3] - meas[:, :3, 3]
    rel = np.einsum("nji,njk->nik", pred[:, :3, :3], meas[:, :3, :3])
    dr = np.degrees(Rotation.from_matrix(rel).as_rotvec())
    return dt, dr


def _pack(X: FloatArray, Z: FloatArray) -> FloatArray:
    return np.concatenate([Rotation.from_matrix(X[:3, :3]).as_rotvec(), X[:3, 3],
                           Rotation.from_matrix(Z[:3, :3]).as_rotvec(), Z[:3, 3]])


def _unpack(x: FloatArray) -> tuple[FloatArray, FloatArray]:
    X = transform(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6])
    Z = transform(Rotation.from_rotvec(x[6:9]).as_matrix(), x[9:12])
    return X, Z


def refine(X0: FloatArray, Z0: FloatArray, B: FloatArray, C: FloatArray, eye_in_hand: bool,
           sigma_mm: float, sigma_deg: float) -> tuple[FloatArray, FloatArray]:
    """Joint least squares over ``X`` and ``Z`` (module doc, step 2)."""
    def residuals(x: FloatArray) -> FloatArray:
        X, Z = _unpack(x)
        dt, dr = pair_errors(X, Z, B, C, eye_in_hand)
        r: FloatArray = np.concatenate([(dt / sigma_mm).ravel(), (dr / sigma_deg).ravel()])
        return r

    sol = least_squares(residuals, _pack(X0, Z0), loss="soft_l1", f_scale=2.0, x_scale="jac",
                        max_nfev=200)
    return _unpack(np.asarray(sol.x, dtype=np.float64))


def _norms(X: FloatArray, Z: FloatArray, B: FloatArray, C: FloatArray,
           eye_in_hand: bool) -> tuple[FloatArray, FloatArray]:
    dt, dr = pair_errors(X, Z, B, C, eye_in_hand)
    return np.linalg.norm(dt, axis=1), np.linalg.norm(dr, axis=1)


def _rms(x: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def difference(A: FloatArray, B: FloatArray) -> dict[str, float]:
    """``{dt_mm, dr_deg}``: translation distance and rotation angle between two transforms."""
    c = float(np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    return {"dt_mm": float(np.linalg.norm(A[:3, 3] - B[:3, 3])), "dr_deg": float(np.degrees(np.arccos(c)))}


def _closed_forms(B: FloatArray, C: FloatArray, eye_in_hand: bool
                  ) -> tuple[dict[str, tuple[FloatArray, FloatArray]], dict[str, str]]:
    import cv2

    ok: dict[str, tuple[FloatArray, FloatArray]] = {}
    failed: dict[str, str] = {}
    for m in HAND_EYE_METHODS + ROBOT_WORLD_METHODS:
        try:
            ok[m] = closed_form(m, B, C, eye_in_hand)
        except cv2.error as exc:
            failed[m] = str(exc).strip().splitlines()[-1]
        except ClosedFormError as exc:
            failed[m] = str(exc)
    return ok, failed


def _proper(T: FloatArray) -> FloatArray | None:
    """``T`` with its rotation projected on SO(3) (SVD) when it is within 0.01 of a rotation
    (max abs entry of ``R^T R - I``, det > 0) and finite; else None. A closed form fed data it
    cannot solve may return a reflection or a non-orthonormal matrix."""
    if not np.all(np.isfinite(T)):
        return None
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > 0.01 or np.linalg.det(R) <= 0.0:
        return None
    u, _, vt = np.linalg.svd(R)
    return transform(u @ vt, T[:3, 3])


def _best_start(forms: dict[str, tuple[FloatArray, FloatArray]], B: FloatArray, C: FloatArray,
                eye_in_hand: bool) -> tuple[str, float, float]:
    """The closed form with the smallest median errors (each kind relative to the best method's),
    and the sigmas (its median errors, floored) the refinement divides by."""
    med = {m: tuple(float(np.median(n)) for n in _norms(X, Z, B, C, eye_in_hand))
           for m, (X, Z) in forms.items()}
    t_min = max(min(v[0] for v in med.values()), 1e-6)
    r_min = max(min(v[1] for v in med.values()), 1e-6)
    best = min(med, key=lambda m: med[m][0] / t_min + med[m][1] / r_min)
    return best, max(med[best][0], 1e-3), max(med[best][1], 1e-4)


def _select(n: int, st: OfflineSettings) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(fit, held-out) indices: at most ``max_pairs`` evenly spread, every ``holdout_every``-th
    of them held out."""
    chosen = np.unique(np.round(np.linspace(0, n - 1, min(n, st.max_pairs))).astype(np.int64))
    k = st.holdout_every
    held = np.array([i for j, i in enumerate(chosen) if k > 0 and j % k == k - 1], dtype=np.int64)
    fit = np.array([i for j, i in enumerate(chosen) if not (k > 0 and j % k == k - 1)], dtype=np.int64)
    return fit, held


def _reject(scores: FloatArray, active: NDArray[np.bool_], limit: int, st: OfflineSettings) -> list[int]:
    """Positions (into ``scores``) to drop this round, worst first, within the cap ``limit``."""
    s = scores[active]
    med = float(np.median(s))
    mad = 1.4826 * float(np.median(np.abs(s - med)))
    thr = med + st.outlier_mads * max(mad, 1e-9)
    bad = [int(i) for i in np.argsort(-scores) if active[i] and scores[i] > thr]
    return bad[:limit]


def solve_offline(pairs: PosePairs, setup: str, path: str, settings: OfflineSettings | None = None,
                  clock: Callable[[], float] = time.perf_counter) -> OfflineResult:
    """X and Z from recorded pairs (module doc). ``path`` names the file in messages.

    Raises:
        SamplesError: too few pairs, degenerate motion (both judged on every pair read), or no
            closed form succeeded.
        ValueError: ``setup`` is not one of :data:`SETUPS`.
    """
    if setup not in SETUPS:
        raise ValueError(f"setup must be one of {SETUPS}, got {setup!r}")
    st = settings or OfflineSettings()
    eye_in_hand = setup == "eye-in-hand"
    t0 = clock()
    check_motion(pairs, path)
    fit_idx, held_idx = _select(len(pairs), st)
    fit = pairs.subset(fit_idx)
    B, C = fit.T_base_from_flange, fit.T_camera_from_target
    forms, failed = _closed_forms(B, C, eye_in_hand)
    if not forms:
        why = "; ".join(f"{m}: {w}" for m, w in failed.items())
        raise SamplesError(path, f"no closed-form hand-eye method succeeded ({why})")
    start, sig_mm, sig_deg = _best_start(forms, B, C, eye_in_hand)
    X, Z = forms[start]
    active = np.ones(len(fit), dtype=bool)
    cap = int(st.max_outlier_fraction * len(fit))
    for _ in range(MAX_REJECTION_ROUNDS):
        X, Z = refine(X, Z, B[active], C[active], eye_in_hand, sig_mm, sig_deg)
        e_mm, e_deg = _norms(X, Z, B, C, eye_in_hand)
        scores = np.hypot(e_mm / sig_mm, e_deg / sig_deg)
        drop = _reject(scores, active, cap - int((~active).sum()), st)
        if not drop:
            break
        active[drop] = False
    else:   # the last round dropped pairs: fit once more without them
        X, Z = refine(X, Z, B[active], C[active], eye_in_hand, sig_mm, sig_deg)
        e_mm, e_deg = _norms(X, Z, B, C, eye_in_hand)
    solve_s = clock() - t0
    per_pair = [PairError(fit.where[i], float(e_mm[i]), float(e_deg[i]), "used" if active[i] else "outlier")
                for i in range(len(fit))]
    validation: dict[str, Any] = {"pairs": len(held_idx), "residual_mm_rms": None, "residual_deg_rms": None}
    if len(held_idx):
        held = pairs.subset(held_idx)
        h_mm, h_deg = _norms(X, Z, held.T_base_from_flange, held.T_camera_from_target, eye_in_hand)
        validation.update(residual_mm_rms=_rms(h_mm), residual_deg_rms=_rms(h_deg))
        per_pair += [PairError(held.where[i], float(h_mm[i]), float(h_deg[i]), "held_out")
                     for i in range(len(held))]
    methods: dict[str, dict[str, Any]] = {m: difference(fx, X) for m, (fx, _) in forms.items()}
    methods.update({m: {"failed": why} for m, why in failed.items()})
    return OfflineResult(setup, X, Z, len(pairs), tuple(per_pair), _rms(e_mm[active]), _rms(e_deg[active]),
                         validation, methods, start, solve_s)
