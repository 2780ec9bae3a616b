"""Multi-pose hand-eye calibration of a fixed stereo camera and markers on the robot's TCP.

The model (eye-to-hand, markers on the tool): for pose ``k`` and marker ``i``,

    y_ki = T_optical_from_robot @ T_robot_from_tcp_k @ p_i

where ``y_ki`` is the marker's triangulated centre (optical frame), ``T_robot_from_tcp_k`` the
pose the arm reports and ``p_i`` the marker's position in the TCP frame. Unknowns:
``Z = T_optical_from_robot`` and the layout ``p`` (camera -> robot and TCP -> markers, jointly).

1. Start: the CAD layout fitted to each pose's markers (Horn, seed 000 eqs 17-21) gives
   ``T_optical_from_plate_k = Z B_k T_tcp_from_plate``; inverted, ``A_k X = Z' B_k'`` with
   ``A_k = T_plate_from_optical_k``, ``X = T_optical_from_robot``, ``Z' = T_plate_from_tcp``,
   ``B_k' = T_tcp_from_robot_k``: the AX = ZB form of robot-world/hand-eye calibration, solved in
   closed form by Shah's Kronecker method (the one behind OpenCV's
   ``calibrateRobotWorldHandEye``, whose mapping is world := optical, cam := plate,
   gripper := TCP).
2. Refine: nonlinear least squares (scipy ``least_squares``, soft-L1 loss) on every 3D marker
   residual over ``Z`` (rotation vector, translation) and every ``p_i`` separately, so each
   marker's own CAD error is recovered, not only the plate's pose. With
   ``SolverSettings.optical_correction`` a second refinement adds a projective warp ``W`` of the
   optical frame (nine numbers, :mod:`hil.geometry.projective`), ``y_ki = W(Z B_k p_i)``: a stereo
   calibration a fraction of a pixel off scales, shears and bends triangulated space, and without
   ``W`` the layout absorbs that (a 0.3 px calibration error put 0.3 mm RMS into a simulated rig's
   layout). The arm's reported translations are the metric reference that makes ``W``
   observable; its undoing is the result's ``optical_correction``, applied to every located
   point when the rig file is used.
3. Robust: a pose whose RMS residual is beyond ``median + k * 1.4826 * MAD`` of all poses (and
   above a floor) is an outlier; the worst is dropped and the fit repeated, one at a time.
4. Held out: every ``holdout_every``-th pose (in canonical order) is not fitted; the model's RMS
   residual on them is the validation error.

Order independence: poses are put in a canonical order (by their reported pose) before anything
else, so a permutation of the input gives the same result bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from hil.errors import GeometryError, HilError
from hil.geometry.projective import WARP_PARAMETERS, ProjectiveCorrection, apply_homography, warp_matrix
from hil.geometry.registration import register_horn
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

FloatArray = NDArray[np.float64]


class RigCalibrationError(HilError):
    """The rig calibration cannot be made from what was collected; the message says why and what
    to do (one line)."""


@dataclass(frozen=True)
class PoseSample:
    """What one still pose gave.

    Attributes:
        index: the pose's number in the procedure (for messages and the file).
        T_robot_from_tcp: the pose the arm reported (mm), at the markers' time.
        markers_optical_mm: (M, 3) the flange markers in layout order, optical frame (NaN: not seen).
    """

    index: int
    T_robot_from_tcp: RigidTransform
    markers_optical_mm: FloatArray


@dataclass(frozen=True)
class PoseResidual:
    """One pose's fit.

    Attributes:
        index: the pose's number.
        residual_mm: RMS distance of its markers to the model, mm.
        residual_deg: angle between the TCP pose its markers give and the model's, deg.
        role: ``used`` (fitted), ``outlier`` (rejected), ``held_out`` (validation only).
    """

    index: int
    residual_mm: float
    residual_deg: float
    role: str


@dataclass(frozen=True)
class HandEyeResult:
    """A multi-pose hand-eye calibration.

    Attributes:
        T_optical_from_robot: the robot base seen from the left camera.
        markers_tcp_mm: (M, 3) the flange-marker layout in the TCP frame.
        poses: per pose, in canonical order.
        residual_mm_rms, residual_deg_rms: RMS over the used poses.
        validation_mm_rms: RMS marker residual over the held-out poses (None: none held out).
        validation_deg_rms: the same in rotation.
        rotation_spread_deg: the largest rotation between two used poses.
        optical_correction: measured -> metric optical points (the stereo calibration's error as
            the arm's motion shows it), or None when not fitted.
        optical_correction_mm: the furthest the correction moves a marker the fit saw, mm.
    """

    T_optical_from_robot: RigidTransform
    markers_tcp_mm: FloatArray
    poses: tuple[PoseResidual, ...]
    residual_mm_rms: float
    residual_deg_rms: float
    validation_mm_rms: float | None
    validation_deg_rms: float | None
    rotation_spread_deg: float
    optical_correction: ProjectiveCorrection | None = None
    optical_correction_mm: float | None = None

    @property
    def outliers(self) -> list[int]:
        return [p.index for p in self.poses if p.role == "outlier"]

    @property
    def poses_used(self) -> int:
        return sum(p.role == "used" for p in self.poses)


@dataclass(frozen=True)
class SolverSettings:
    """Thresholds of :func:`solve_hand_eye`.

    Attributes:
        min_poses: fewest poses accepted (fitted plus held out).
        min_rotation_deg: the poses must rotate at least this much between them ...
        min_axis_spread: ... about at least two clearly different axes: the second singular value
            of the (angle-weighted) rotation-axis matrix over the first must reach this.
        holdout_every: every n-th pose is held out for validation (0: none).
        outlier_mads: rejection threshold, in robust standard deviations above the median.
        outlier_floor_mm: a pose under this RMS residual is never an outlier.
        max_outlier_fraction: never reject more than this fraction of the fitted poses.
        depth_weight: weight of the residuals' optical z (depth) component (see :func:`refine`).
        optical_correction: also fit the stereo calibration's error as a projective warp of space
            (:mod:`hil.geometry.projective`), so it stays out of the layout.
        max_optical_correction_mm: refuse a warp whose undoing moves a seen marker further.
    """

    min_poses: int = 8
    min_rotation_deg: float = 10.0
    min_axis_spread: float = 0.25
    holdout_every: int = 4
    outlier_mads: float = 4.0
    outlier_floor_mm: float = 0.3
    max_outlier_fraction: float = 0.25
    depth_weight: float = 1.0
    optical_correction: bool = False
    max_optical_correction_mm: float = 5.0


def canonical_order(samples: Sequence[PoseSample]) -> list[PoseSample]:
    """The samples sorted by their reported pose (translation, then rotation vector, rounded to
    1 um / 1 urad), then by index: the order every later step uses."""
    def key(s: PoseSample) -> tuple[float, ...]:
        T = s.T_robot_from_tcp
        return (*np.round(T.t, 3).tolist(), *np.round(T.as_rotvec(), 6).tolist(), float(s.index))
    return sorted(samples, key=key)


def check_rotation_diversity(samples: Sequence[PoseSample], settings: SolverSettings) -> float:
    """Refuse pose sets that cannot fix the calibration: rotations too small, or all about one axis
    (a rotation axis leaves the layout's and the base's translation along it undetermined).
    Returns the largest rotation between two poses, deg.

    Raises:
        RigCalibrationError: naming the single axis (robot base frame) when degenerate.
    """
    R0 = samples[0].T_robot_from_tcp.R
    rel = [RigidTransform(s.T_robot_from_tcp.R @ R0.T, np.zeros(3)) for s in samples[1:]]
    pairs = [RigidTransform(a.T_robot_from_tcp.R @ b.T_robot_from_tcp.R.T, np.zeros(3))
             for i, a in enumerate(samples) for b in samples[i + 1:]]
    spread = max((math.degrees(p.rotation_angle_rad()) for p in pairs), default=0.0)
    if spread < settings.min_rotation_deg:
        raise RigCalibrationError(
            f"poses too similar: the largest rotation between two poses is {spread:.1f} deg "
            f"(need >= {settings.min_rotation_deg:g} deg); tilt the tool more between poses")
    vecs = np.array([p.as_rotvec() for p in pairs + rel])
    sv = np.linalg.svd(vecs, compute_uv=False)
    ratio = float(sv[1] / sv[0]) if sv[0] > 0 else 0.0
    if ratio < settings.min_axis_spread:
        _, _, vt = np.linalg.svd(vecs)
        axis = vt[0] / np.linalg.norm(vt[0])
        raise RigCalibrationError(
            "degenerate rotation axes: the poses rotate (almost) only about the axis "
            f"{np.round(axis, 2).tolist()} (robot base frame; spread ratio {ratio:.2f} < "
            f"{settings.min_axis_spread:g}); add poses tilted about a perpendicular axis")
    return spread


def _usable(samples: Sequence[PoseSample]) -> None:
    for s in samples:
        seen = int(np.all(np.isfinite(s.markers_optical_mm), axis=1).sum())
        if seen < 3:
            raise RigCalibrationError(f"markers not seen: pose {s.index} has {seen} flange markers "
                                      "identified (need >= 3)")


def shah_robot_world_hand_eye(A: Sequence[RigidTransform],
                              B: Sequence[RigidTransform]) -> tuple[RigidTransform, RigidTransform]:
    """Closed-form ``A_k X = Z B_k`` (Shah 2013, "Solving the robot-world/hand-eye calibration
    problem using the Kronecker product"): the rotations from the null vector of the stacked
    ``[I (x) R_A, -(R_B^T (x) I)] [vec R_X; vec R_Z] = 0`` (column-major vec), each scaled to
    det 1 and projected on SO(3); then the translations from the linear
    ``R_A t_X - t_Z = R_Z t_B - t_A``. Returns ``(X, Z)``. (OpenCV's ``calibrateRobotWorldHandEye``
    implements the same method; the OpenCV 5 wheels the project installs do not ship it.)"""
    I3 = np.eye(3)
    rows = [np.hstack([np.kron(I3, a.R), -np.kron(b.R.T, I3)]) for a, b in zip(A, B, strict=True)]
    _, _, vt = np.linalg.svd(np.vstack(rows))
    v = vt[-1]
    Rx = v[:9].reshape(3, 3, order="F")
    Rz = v[9:].reshape(3, 3, order="F")
    scale = np.cbrt(np.linalg.det(Rx))
    Rx, Rz = _nearest_rotation(Rx / scale), _nearest_rotation(Rz / scale)
    M = np.vstack([np.hstack([a.R, -I3]) for a in A])
    rhs = np.concatenate([Rz @ b.t - a.t for a, b in zip(A, B, strict=True)])
    t = np.linalg.lstsq(M, rhs, rcond=None)[0]
    return RigidTransform(Rx, t[:3]), RigidTransform(Rz, t[3:])


def _nearest_rotation(R: FloatArray) -> FloatArray:
    """The rotation nearest to ``R`` (Frobenius; SVD)."""
    u, _, vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(u @ vt))
    out: FloatArray = u @ np.diag([1.0, 1.0, d]) @ vt
    return out


def initial_estimate(samples: Sequence[PoseSample],
                     layout_tcp_mm: FloatArray) -> tuple[RigidTransform, FloatArray]:
    """``(T_optical_from_robot, layout in the TCP frame)`` from the CAD layout: Horn per pose gives
    ``T_optical_from_plate_k``, then the robot-world/hand-eye solver (Shah) with ``A_k =
    T_plate_from_optical_k``, ``B_k = T_tcp_from_robot_k``: ``A_k X = Z B_k`` with ``X =
    T_optical_from_robot`` and ``Z = T_plate_from_tcp``.

    Raises:
        RigCalibrationError: a pose's markers do not fix a plate pose.
    """
    A, B = [], []
    for s in samples:
        ok = np.all(np.isfinite(s.markers_optical_mm), axis=1)
        try:
            T = register_horn(s.markers_optical_mm[ok], layout_tcp_mm[ok]).T_fixed_from_moving
        except GeometryError as exc:
            raise RigCalibrationError(f"pose {s.index}: its markers do not fix a pose: {exc}") from None
        A.append(T.inverse())
        B.append(s.T_robot_from_tcp.inverse())
    T_optical_from_robot, T_plate_from_tcp = shah_robot_world_hand_eye(A, B)
    return T_optical_from_robot, T_plate_from_tcp.inverse().apply(layout_tcp_mm)


def _pack(Z: RigidTransform, layout: FloatArray, warp: FloatArray | None) -> FloatArray:
    parts = [Z.as_rotvec(), Z.t, layout.ravel()]
    return np.concatenate(parts if warp is None else [*parts, warp])


def _unpack(x: FloatArray, m: int, warp: bool) -> tuple[RigidTransform, FloatArray, FloatArray | None]:
    end = 6 + 3 * m
    return (RigidTransform(rotvec_to_matrix(x[:3]), x[3:6]), x[6:end].reshape(m, 3),
            x[end:end + WARP_PARAMETERS] if warp else None)


@dataclass(frozen=True)
class RigModel:
    """What the hand-eye fit estimates: ``Z = T_optical_from_robot``, the layout (M, 3, TCP frame,
    mm) and, with an optical correction, the warp ``W`` (4x4, metric -> measured optical; None:
    the stereo calibration is taken as exact). A marker is predicted at ``W(Z @ B_k @ p_i)``."""

    Z: RigidTransform
    layout: FloatArray
    warp: FloatArray | None = None

    def predict(self, T_robot_from_tcp: RigidTransform, layout: FloatArray | None = None) -> FloatArray:
        """Where the camera should see the markers (``layout`` rows, default all) at this pose."""
        pts = (self.Z @ T_robot_from_tcp).apply(self.layout if layout is None else layout)
        return pts if self.warp is None else apply_homography(self.warp, pts)

    def metric(self, measured_mm: FloatArray) -> FloatArray:
        """Measured points (optical frame) with the warp undone (unchanged without one)."""
        if self.warp is None:
            return measured_mm
        undo = np.asarray(np.linalg.inv(self.warp), dtype=np.float64)
        return apply_homography(undo, measured_mm)


def refine(samples: Sequence[PoseSample], start: RigModel, center_mm: FloatArray | None = None,
           scale_mm: float = 0.2, depth_weight: float = 1.0) -> RigModel:
    """Least squares on every 3D marker residual over ``Z``, each ``p_i`` and, when ``start`` has
    a warp, its nine parameters about ``center_mm`` (:func:`hil.geometry.projective.warp_matrix`:
    the stereo calibration's error as a projective map of space, with no rigid part, which is
    ``Z``'s), soft-L1 loss of scale ``scale_mm`` so a few bad markers do not pull the fit. The
    residual's optical z (depth) component is multiplied by ``depth_weight``: a stereo rig
    measures depth about distance / baseline times worse than across (whitening by that ratio is
    the weighted least squares of triangulated points). The robot's reported translations are the
    metric reference that makes the warp's scale and shear observable."""
    m = start.layout.shape[0]
    has_warp = start.warp is not None
    c = np.zeros(3) if center_mm is None else np.asarray(center_mm, dtype=np.float64)
    B_R = np.array([s.T_robot_from_tcp.R for s in samples])
    B_t = np.array([s.T_robot_from_tcp.t for s in samples])
    Y = np.array([s.markers_optical_mm for s in samples])     # (K, M, 3)
    seen = np.all(np.isfinite(Y), axis=2)                      # (K, M)

    def residuals(x: FloatArray) -> FloatArray:
        Z, p, w = _unpack(x, m, has_warp)
        robot = np.einsum("kab,mb->kma", B_R, p) + B_t[:, None, :]
        pred = robot @ Z.R.T + Z.t
        if w is not None:
            pred = apply_homography(warp_matrix(c, w), pred.reshape(-1, 3)).reshape(pred.shape)
        d = (pred - Y)[seen]
        d[:, 2] *= depth_weight
        r: FloatArray = d.ravel()
        return r

    w0 = None if start.warp is None else _warp_params(start.warp, c)
    sol = least_squares(residuals, _pack(start.Z, start.layout, w0), loss="soft_l1", f_scale=scale_mm,
                        x_scale="jac", max_nfev=200 if not has_warp else 400)
    Z, p, w = _unpack(np.asarray(sol.x, dtype=np.float64), m, has_warp)
    return RigModel(Z, p, None if w is None else warp_matrix(c, w))


def _warp_params(warp: FloatArray, center_mm: FloatArray) -> FloatArray:
    """The nine parameters ``p`` with ``warp_matrix(center_mm, p) == warp``: the inverse of
    :func:`~hil.geometry.projective.warp_matrix` (a restart's starting point)."""
    to_c, from_c = np.eye(4), np.eye(4)
    to_c[:3, 3], from_c[:3, 3] = -center_mm, center_mm
    about = to_c @ warp @ from_c
    about = about / about[3, 3]
    S = about[:3, :3] - np.eye(3)
    return np.array([S[0, 0], S[1, 1], S[2, 2], S[0, 1], S[0, 2], S[1, 2], *about[3, :3]])


def pose_residual(s: PoseSample, model: RigModel, role: str) -> PoseResidual:
    """RMS marker distance (mm) and rotation (deg) between what pose ``s`` saw and the model."""
    ok = np.all(np.isfinite(s.markers_optical_mm), axis=1)
    layout = model.layout[ok]
    d = model.predict(s.T_robot_from_tcp, layout) - s.markers_optical_mm[ok]
    mm = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
    T_pred = model.Z @ s.T_robot_from_tcp
    try:
        T_meas = register_horn(model.metric(s.markers_optical_mm[ok]), layout).T_fixed_from_moving
        deg = math.degrees((T_pred.inverse() @ T_meas).rotation_angle_rad())
    except GeometryError:
        deg = float("nan")
    return PoseResidual(s.index, mm, deg, role)


def _rms(xs: Sequence[float]) -> float:
    return float(np.sqrt(np.mean(np.square(xs)))) if xs else float("nan")


def _worst_outlier(res: Sequence[PoseResidual], settings: SolverSettings) -> int | None:
    """Position in ``res`` of the worst pose beyond the robust threshold, or None."""
    r = np.array([p.residual_mm for p in res])
    med = float(np.median(r))
    mad = 1.4826 * float(np.median(np.abs(r - med)))
    limit = max(med + settings.outlier_mads * max(mad, 0.01), settings.outlier_floor_mm)
    worst = int(np.argmax(r))
    return worst if r[worst] > limit else None


def solve_hand_eye(samples: Sequence[PoseSample], layout_tcp_mm: FloatArray,
                   settings: SolverSettings | None = None) -> HandEyeResult:
    """Camera -> robot and TCP -> markers from still poses (see the module doc).

    Args:
        samples: one per pose, markers in the order of ``layout_tcp_mm``.
        layout_tcp_mm: (M, 3) the CAD layout in the TCP frame (the starting point).
        settings: thresholds (default :class:`SolverSettings`).

    Raises:
        RigCalibrationError: too few poses, markers not seen at a pose, poses too similar or
            rotating about one axis only (the axis is named), or too many outliers.
    """
    st = settings or SolverSettings()
    layout_tcp_mm = np.asarray(layout_tcp_mm, dtype=np.float64)
    if len(samples) < st.min_poses:
        raise RigCalibrationError(f"too few poses: {len(samples)} collected, need >= {st.min_poses}")
    _usable(samples)
    ordered = canonical_order(samples)
    k = st.holdout_every
    held = [s for i, s in enumerate(ordered) if k > 0 and i % k == k - 1]
    fit = [s for i, s in enumerate(ordered) if not (k > 0 and i % k == k - 1)]
    spread = check_rotation_diversity(fit, st)
    center = _center(fit)
    model = refine(fit, RigModel(*initial_estimate(fit, layout_tcp_mm)), depth_weight=st.depth_weight)
    if st.optical_correction:
        model = refine(fit, RigModel(model.Z, model.layout, np.eye(4)), center, depth_weight=st.depth_weight)
    outliers: list[PoseSample] = []
    max_out = int(st.max_outlier_fraction * len(fit))
    while True:
        res = [pose_residual(s, model, "used") for s in fit]
        worst = _worst_outlier(res, st)
        if worst is None:
            break
        if len(outliers) >= max_out:
            raise RigCalibrationError(
                f"too many outliers: more than {max_out} of {len(fit) + len(outliers)} poses disagree "
                f"with the fit (worst: pose {res[worst].index}, {res[worst].residual_mm:.2f} mm); "
                "check the marker plate is rigid and the arm reports the pose of the markers' time")
        outliers.append(fit.pop(worst))
        check_rotation_diversity(fit, st)
        model = refine(fit, model, center, depth_weight=st.depth_weight)
    correction, moved_mm = _correction(model, fit, st)
    res_out = [pose_residual(s, model, "outlier") for s in outliers]
    res_held = [pose_residual(s, model, "held_out") for s in held]
    by_sample = {id(s): r for s, r in zip(fit + outliers + held, res + res_out + res_held, strict=True)}
    return HandEyeResult(
        T_optical_from_robot=model.Z, markers_tcp_mm=model.layout,
        poses=tuple(by_sample[id(s)] for s in ordered),
        residual_mm_rms=_rms([r.residual_mm for r in res]),
        residual_deg_rms=_rms([r.residual_deg for r in res]),
        validation_mm_rms=_rms([r.residual_mm for r in res_held]) if res_held else None,
        validation_deg_rms=_rms([r.residual_deg for r in res_held]) if res_held else None,
        rotation_spread_deg=spread,
        optical_correction=correction, optical_correction_mm=moved_mm,
    )


def _center(samples: Sequence[PoseSample]) -> FloatArray:
    """The mean of every seen marker (optical frame, mm): the warp's centre."""
    pts = np.concatenate([s.markers_optical_mm for s in samples])
    out: FloatArray = np.mean(pts[np.all(np.isfinite(pts), axis=1)], axis=0)
    return out


def _correction(model: RigModel, fit: Sequence[PoseSample],
                st: SolverSettings) -> tuple[ProjectiveCorrection | None, float | None]:
    """The fitted warp's undoing and the furthest it moves a marker the fit saw (mm), checked
    against ``st.max_optical_correction_mm`` ((None, None) without a warp).

    Raises:
        RigCalibrationError: the correction moves a seen marker further than the bound.
    """
    if model.warp is None:
        return None, None
    correction = ProjectiveCorrection.undoing(model.warp)
    pts = np.concatenate([s.markers_optical_mm for s in fit])
    moved = correction.displacement_mm(pts[np.all(np.isfinite(pts), axis=1)])
    if moved > st.max_optical_correction_mm:
        raise RigCalibrationError(
            f"the stereo calibration disagrees with the arm's motion by up to {moved:.2f} mm over the "
            f"calibration volume (bound {st.max_optical_correction_mm} mm, [rig_calibration] "
            "max_optical_correction_mm): recalibrate the cameras (hil calibrate) and check the "
            "calibration file is this camera's")
    return correction, moved
