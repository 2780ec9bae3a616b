"""Time delay of a device's signal against a known reference, with its uncertainty.

The reference ``c(t)`` is the commanded motion (:class:`Reference`). A device that sees the
motion reports ``y_i ~ g c(t_i - tau) + b`` at its stamps ``t_i``.
``tau`` is found as the peak of the normalised cross-correlation of ``y`` with the delayed
reference over a grid of candidate delays (1 ms steps within ``+-max_ms``) -- the least-squares
fit of gain and bias at each candidate, so unevenly sampled devices need no resampling -- then
refined by a parabola through the peak and its neighbours. The 1-sigma uncertainty is the
Gauss-Newton one of the fitted delay: ``sigma_tau = sigma_res / (|g| sqrt(sum c'(t_i - tau)^2))``
(PLUS's temporal calibration also cross-correlates position signals; this is our own version,
fitted against the commands rather than between two devices).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.rigcal.handeye import RigCalibrationError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DelayEstimate:
    """A device's delay against the reference.

    Attributes:
        delay_ms: ``tau``, ms (positive: the device's stamps are late).
        sigma_ms: 1-sigma uncertainty, ms.
        correlation: normalised correlation at the peak (1: a perfect fit).
        samples: samples used.
    """

    delay_ms: float
    sigma_ms: float
    correlation: float
    samples: int


class Reference:
    """The commanded signal. The arm holds each command ``v[k]`` from its send time ``t[k]`` until
    the next one (a zero-order hold); for delay fitting that staircase is replaced by the line
    through the middles of its steps -- the hold's low-frequency content (a hold delays a smooth
    signal by half its step) -- which is continuous, so the fit's error is smooth in the delay and
    devices sampled in step with the commands do not see the stairs."""

    def __init__(self, t_ns: FloatArray, values: FloatArray) -> None:
        order = np.argsort(t_ns, kind="stable")
        t = np.asarray(t_ns, dtype=np.float64)[order]
        self.v = np.asarray(values, dtype=np.float64)[order]
        steps = np.diff(t)
        last = float(np.median(steps)) if len(steps) else 0.0
        self.t = t + 0.5 * np.append(steps, last)   # middle of each hold

    def at(self, t_ns: FloatArray) -> FloatArray:
        """The signal at ``t_ns`` (linear between step middles, constant beyond the ends)."""
        out: FloatArray = np.interp(t_ns, self.t, self.v)
        return out

    def slope_at(self, t_ns: FloatArray, h_ns: float = 2e6) -> FloatArray:
        """d/dt of :meth:`at`, per second (central difference over +-``h_ns``)."""
        out: FloatArray = (self.at(t_ns + h_ns) - self.at(t_ns - h_ns)) / (2 * h_ns * 1e-9)
        return out


def _fit(y: FloatArray, c: FloatArray) -> tuple[float, float, float]:
    """(gain, bias, residual sum of squares) of ``y ~ g c + b``."""
    A = np.column_stack([c, np.ones_like(c)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ coef
    return float(coef[0]), float(coef[1]), float(r @ r)


def estimate_delay(ref: Reference, t_ns: FloatArray, y: FloatArray, max_ms: float,
                   device: str) -> DelayEstimate:
    """The delay of ``(t_ns, y)`` against ``ref`` (see the module doc).

    Samples whose delayed reference time falls outside the reference's span (for any candidate
    delay) are left out.

    Raises:
        RigCalibrationError: too few samples, a flat signal, or the best delay on the search edge.
    """
    t = np.asarray(t_ns, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = np.isfinite(t) & np.isfinite(y)
    ok &= (t - max_ms * 1e6 >= ref.t[0]) & (t + max_ms * 1e6 <= ref.t[-1])
    t, y = t[ok], y[ok]
    if len(t) < 10:
        raise RigCalibrationError(f"temporal calibration: only {len(t)} {device} samples during the "
                                  "motion (need >= 10); is the device streaming?")
    if float(np.std(y)) < 1e-6:
        raise RigCalibrationError(f"temporal calibration: the {device} signal does not move")
    taus = np.arange(-max_ms, max_ms + 0.5, 1.0)
    sse = np.array([_fit(y, ref.at(t - d * 1e6))[2] for d in taus])
    k = int(np.argmin(sse))
    if k == 0 or k == len(taus) - 1:
        raise RigCalibrationError(f"temporal calibration: the {device} delay is at the edge of the "
                                  f"+-{max_ms:g} ms search ([rig_calibration.temporal] max_offset_ms)")
    a, b, c = sse[k - 1], sse[k], sse[k + 1]
    denom = a - 2 * b + c
    tau_ms = float(taus[k] + (0.5 * (a - c) / denom if denom > 0 else 0.0))
    c_tau = ref.at(t - tau_ms * 1e6)
    g, _, rss = _fit(y, c_tau)
    dc_dt = ref.slope_at(t - tau_ms * 1e6)
    sigma_res = math.sqrt(rss / max(len(t) - 3, 1))
    info = float(np.sum((g * dc_dt) ** 2))
    sigma_ms = 1e3 * sigma_res / math.sqrt(info) if info > 0 else float("inf")
    corr = float(np.corrcoef(y, c_tau)[0, 1]) if np.std(c_tau) > 0 else 0.0
    return DelayEstimate(tau_ms, sigma_ms, abs(corr), len(t))
