"""COMPENSATE's setpoint from the loop's predictor (``[procedure.compensation] predictor``,
docs/prediction.md "In the loop").

The servo loop extrapolates a setpoint in a straight line: at command time ``t`` it commands
``pose(h) = (exp(w h) R0, t0 + v h)`` with ``h = t - exposure + lead`` (capped at the maximum
horizon; hil/servo/loop.py). A learning predictor forecasts a curve, so the setpoint handed to the
loop is the *secant* of the predicted TCP path over the horizons the loop will use it for: from
``h_a`` (the horizon at publication) to ``h_b = h_a + one camera period`` (the next pair's
setpoint replaces it then), both capped. The TCP pose at a horizon is the plan's chain
(:meth:`Estimate.desired_tcp_robot_local`) applied to the entry-centred change whose
translation is the predictor's forecast of the entry's displacement and whose rotation is the
alpha-beta filter's (the predictors forecast positions, not attitudes). The loop's line then
passes through the predicted poses at ``h_a`` and ``h_b``.

Nothing here blocks: two predictions, then the compiled setpoint chain
(:meth:`Estimate.setpoint_of_line`, numpy when the kernel is not built).
"""

from __future__ import annotations

import math

import numpy as np

from hil.controller.estimate import Estimate, FloatArray
from hil.geometry.transform import RigidTransform, rotvec_to_matrix

__all__ = ["MIN_SECANT_S", "predicted_setpoint"]

#: the secant's shortest time base, s (below it the loop's line is not defined well enough)
MIN_SECANT_S = 1e-3


def predicted_setpoint(est: Estimate, exposure_t_ns: int, now_ns: int, lead_s: float, max_horizon_s: float
                       ) -> tuple[RigidTransform, FloatArray, FloatArray] | None:
    """The tracking setpoint (TCP pose at the exposure, robot frame, mm; linear velocity mm/s;
    angular velocity rad/s, robot frame) whose straight line through the loop's horizons is the
    secant of the predicted path (module doc), or None when the predictor does not answer for this
    pair: none configured, warming up, holding after a fallback, its last sample not this pair's
    (the pair's change was refused), or no time base (``max_horizon_s`` below
    :data:`MIN_SECANT_S`). On None the caller uses the alpha-beta filter's setpoint
    (:meth:`Estimate.tracking_setpoint`), which is the documented fallback.

    Raises:
        GeometryError: the motion filter has no sample yet.
    """
    cp = est.filter.predictor
    if cp is None or not cp.predicting or cp.last_t_ns != exposure_t_ns:
        return None
    period_s = cp.predictor.period_s
    h_a = min(max((now_ns - exposure_t_ns) * 1e-9 + lead_s, 0.0), max_horizon_s)
    h_b = min(h_a + period_s, max_horizon_s)
    if h_b - h_a < MIN_SECANT_S:   # already at the cap: the secant that ends there
        h_a = max(h_b - period_s, 0.0)
    dt_s = h_b - h_a
    if dt_s < MIN_SECANT_S:
        return None
    # the entry-centred change as a line in h through the prediction at h_a and h_b (translation)
    # and along the filter (rotation vector, linear in h already)
    x, v = est.filter.vectors()
    p_a, p_b = cp.predict_mm(h_a), cp.predict_mm(h_b)
    v_line = v.copy()
    v_line[:3] = (p_b - p_a) / dt_s
    x_line = x.copy()
    x_line[:3] = p_a - v_line[:3] * h_a
    D_a, vel, w = est.setpoint_of_line(x_line, v_line, h_a, h_b)
    # a product of rotations and a fresh translation: valid by construction (no re-checks)
    return RigidTransform._composed(_rotation_back(w, h_a) @ D_a.R, D_a.t - vel * h_a), vel, w


def _rotation_back(w: FloatArray, h_s: float) -> FloatArray:
    """``exp(-w h)`` as a 3 x 3 matrix (Rodrigues, as :func:`rotvec_to_matrix` of ``-w * h``, in
    scalar arithmetic: a tenth of its time on the pair path; identity below 1e-12 rad)."""
    a, b, c = (-h_s * w).tolist()
    theta = math.hypot(a, b, c)
    if not theta >= 1e-12:   # also NaN: the caller's checks downstream refuse the setpoint
        return rotvec_to_matrix(np.array([a, b, c])) if not math.isfinite(theta) else np.eye(3)
    x, y, z = a / theta, b / theta, c / theta
    s, k = math.sin(theta), 1.0 - math.cos(theta)
    return np.array([[1.0 - k * (y * y + z * z), -s * z + k * x * y, s * y + k * x * z],
                     [s * z + k * x * y, 1.0 - k * (x * x + z * z), -s * x + k * y * z],
                     [-s * y + k * x * z, s * x + k * y * z, 1.0 - k * (x * x + y * y)]])
