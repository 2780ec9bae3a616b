"""A recorded trace driving the deformable body (``[simulation.body.trace]``, docs/traces.md).

What a trace drives, by what it holds (:class:`hil.io.traces.Trace`):

- a **surrogate** (1-D, the surrogate and paired formats): the breathing signal ``s``, normalised
  so its 5th percentile is 0 (end-exhale) and its 95th is 1 (``invert_surrogate`` when it falls on
  inhale);
- a **tumour** (6-DoF and paired formats): the target's displacement directly (translations only;
  the point target has no orientation), relative to the trace's end-exhale position (the value
  a least-squares line of the tumour on ``s`` takes at ``s = 0``); without a surrogate (6-DoF),
  ``s`` is the tumour's own normalised motion along its first principal axis, signed so that
  inhale moves it inferior (image -y), as liver and lung targets do;
- **recorded skin points** (points CSV): the skin at the recorded places; between them the
  displacement is interpolated over the skin's (x, y) by a thin-plate spline (Bookstein 1989),
  exact at the recorded points, affine far from them; ``s`` is their mean normalised motion
  along each point's first principal axis, signed anterior (+z).

The trace's time runs from ``start_s`` (default: a seeded end-exhale of the trace) with world
time and wraps at the trace's end. During a breath-hold ``s`` eases to the hold's level and a recorded
target to its position at that level, plus the hold's reproducibility offset
(:class:`drivers.sim.body.TargetMotion`). The model's coughs and baseline wander are not added:
the recording has its own.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from drivers.sim.body import BodyPhantom, BreathingSignal, DeformableBody, TargetMotion
from drivers.sim.motion import PatientMotion, stream_rng
from hil.config.body import BodyTraceConfig
from hil.config.simulation import SimulationConfig
from hil.errors import InputFileError
from hil.geometry.thin_plate import thin_plate_weights
from hil.io.traces import Trace, read_trace, resample

FloatArray = NDArray[np.float64]

#: a trace shorter than this cannot drive a procedure (registration to lock takes ~10 s)
MIN_TRACE_S = 20.0
#: default start: seeded within the trace, leaving this much after it
START_MARGIN_S = 120.0
#: default start: at an end-exhale, a local minimum of the normalised signal below this
EXHALE_LEVEL = 0.1


def normalise(series: FloatArray) -> tuple[FloatArray, float, float]:
    """``(series - p5) / (p95 - p5)`` and the two percentiles; a flat series is refused
    (ValueError)."""
    lo, hi = (float(v) for v in np.percentile(series, [5.0, 95.0]))
    if not hi - lo > 1e-9:
        raise ValueError("the trace does not move (5th and 95th percentiles equal)")
    out: FloatArray = np.asarray((series - lo) / (hi - lo), dtype=np.float64)
    return out, lo, hi


def principal_projection(xyz: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Projection of (N, 3) positions on their first principal axis (centred), and the axis."""
    c = xyz - xyz.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    axis: FloatArray = vt[0]
    proj: FloatArray = c @ axis
    return proj, axis


def line_on_signal(series: FloatArray, s: FloatArray) -> FloatArray:
    """The least-squares line of each column of ``series`` (N, k) on ``s`` (N,): (2, k), the value
    at ``s = 0`` (end-exhale) and the change per unit ``s``."""
    A = np.column_stack([np.ones_like(s), s])
    coef: FloatArray = np.asarray(np.linalg.lstsq(A, series, rcond=None)[0], dtype=np.float64)
    return coef


class TraceSignal:
    """The breathing signal from a recorded series ``s`` on a uniform grid, holds included."""

    def __init__(self, t_s: FloatArray, s: FloatArray, start_s: float, motion: PatientMotion,
                 period_s: float) -> None:
        self._t0 = float(t_s[0])
        self._dt = float(t_s[1] - t_s[0])
        self._s = s
        self._duration_s = self._dt * (len(s) - 1)
        self.start_s = start_s
        self.motion = motion
        self._period_s = period_s

    @property
    def period_s(self) -> float:
        return self._period_s

    def index(self, t_s: float) -> tuple[int, float]:
        """Grid index and fraction of world time ``t_s`` in the trace (wrapping at its end)."""
        tt = (self.start_s + t_s) % self._duration_s
        x = tt / self._dt
        i = min(int(x), len(self._s) - 2)
        return i, x - i

    def sample(self, series: FloatArray, t_s: float) -> FloatArray:
        """Linear interpolation of ``series`` (on the trace's grid) at world time ``t_s``."""
        i, f = self.index(t_s)
        out: FloatArray = (1.0 - f) * series[i] + f * series[i + 1]
        return out

    def raw(self, t_s: float) -> float:
        return float(self.sample(self._s, t_s))

    def s(self, t_s: float) -> float:
        w, i = self.motion.hold_at(t_s)
        free = self.raw(t_s)
        if w <= 0.0:
            return free
        return (1.0 - w) * free + w * self.motion.holds[i].level

    def hold(self, t_s: float) -> tuple[float, int]:
        return self.motion.hold_at(t_s)


class TraceTargetDrive:
    """A recorded tumour drives the target: its displacement from the trace's end-exhale
    position, easing during a breath-hold to its position at the hold's level (the tumour's line
    on ``s``) plus the hold's reproducibility offset."""

    def __init__(self, signal: TraceSignal, target_mm: FloatArray, s: FloatArray,
                 motion: TargetMotion) -> None:
        self._line = line_on_signal(target_mm, s)      # (2, 3)
        self._disp: FloatArray = target_mm - self._line[0]
        self.signal = signal
        self.motion = motion

    def target_displacement_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray:
        free = self.signal.sample(self._disp, t_s)
        w, i = self.signal.hold(t_s)
        if w <= 0.0:
            return free
        level = self.signal.motion.holds[i].level
        at_level = level * self._line[1]
        out: FloatArray = (1.0 - w) * free + w * at_level + self.motion.hold_part_mm(signal, t_s)
        return out


class TracePointsDrive:
    """Recorded skin points drive the skin: their displacements from end-exhale, interpolated at
    the query positions by a thin-plate spline over the skin's (x, y)."""

    def __init__(self, signal: TraceSignal, displacements_mm: FloatArray, per_s_mm: FloatArray,
                 W: FloatArray) -> None:
        self.signal = signal
        self._disp = displacements_mm          # (N, n, 3) on the trace grid, from end-exhale
        self._per_s = per_s_mm                 # (n, 3): each point's line on s, change per unit s
        self._W = W

    def skin_displacement_mm(self, signal: BreathingSignal, t_s: float) -> FloatArray:
        d = self.signal.sample(self._disp, t_s)            # (n, 3)
        w, i = self.signal.hold(t_s)
        if w > 0.0:
            d = (1.0 - w) * d + w * self.signal.motion.holds[i].level * self._per_s
        out: FloatArray = self._W @ d
        return out


def _start_s(cfg: BodyTraceConfig, t_s: FloatArray, s: FloatArray, seed: int) -> float:
    """Where in the trace world time 0 falls: ``start_s`` when given, else a seeded end-exhale of
    the trace (a local minimum of ``s`` below :data:`EXHALE_LEVEL`) at least
    :data:`START_MARGIN_S` before its end — a procedure starts with the patient registered at
    end-exhale, as the CT was taken — or, without one, a seeded time in that span."""
    if cfg.start_s is not None:
        return cfg.start_s
    span = max(float(t_s[-1] - t_s[0]) - START_MARGIN_S, 0.0)
    rng = stream_rng(seed, "trace_start")
    inner = s[1:-1]
    minima = np.flatnonzero((inner <= s[:-2]) & (inner <= s[2:]) & (inner <= EXHALE_LEVEL)) + 1
    minima = minima[(t_s[minima] - t_s[0]) <= span]
    if len(minima):
        return float(t_s[int(rng.choice(minima))] - t_s[0])
    return float(rng.uniform(0.0, span)) if span > 0.0 else 0.0


def _period_s(t_s: FloatArray, s: FloatArray, default_s: float) -> float:
    """The dominant period of ``s`` between 1.5 and 12 s (its spectrum's peak), or the default."""
    dt = float(t_s[1] - t_s[0])
    f = np.fft.rfftfreq(len(s), dt)
    p = np.abs(np.fft.rfft(s - s.mean()))
    band = (f > 1.0 / 12.0) & (f < 1.0 / 1.5)
    if not band.any() or not p[band].max() > 0.0:
        return default_s
    return float(1.0 / f[band][np.argmax(p[band])])


def trace_body(sim: SimulationConfig, phantom: BodyPhantom, motion: PatientMotion,
               trace: Trace) -> DeformableBody:
    """The deformable body driven by ``trace`` (module doc)."""
    cfg = sim.body.trace
    tr = resample(trace, cfg.rate_hz)
    if tr.duration_s < MIN_TRACE_S:
        raise InputFileError(
            trace.path, f"{tr.duration_s:.1f} s long; a procedure needs at least {MIN_TRACE_S:g} s")
    try:
        s, target, points = _signals(tr, cfg)
    except ValueError as exc:
        raise InputFileError(trace.path, str(exc)) from None
    signal = TraceSignal(tr.time_s, s, _start_s(cfg, tr.time_s, s, sim.seed), motion,
                         _period_s(tr.time_s, s, sim.breathing.period_s))
    body = DeformableBody(sim.body, sim.seed, phantom.markers_mm, phantom.entry_mm, phantom.target_mm,
                          sim.patient.torso_radius_mm, signal)
    if target is not None:
        body.target = TraceTargetDrive(signal, target, s, body.target_motion)
    if points is not None:
        places = _places(tr, cfg)
        names = sorted(points)
        try:
            W = thin_plate_weights(np.array([places[n] for n in names]), body.query.xy_mm)
        except ValueError as exc:
            raise InputFileError(trace.path, str(exc)) from None
        lines = [line_on_signal(points[n], s) for n in names]
        disp = np.stack([points[n] - ln[0] for n, ln in zip(names, lines, strict=True)], axis=1)  # (N, n, 3)
        body.skin = TracePointsDrive(signal, disp, np.array([ln[1] for ln in lines]), W)
    return body


def _places(tr: Trace, cfg: BodyTraceConfig) -> dict[str, tuple[float, float]]:
    places = dict(tr.point_places_mm or {})
    places.update(cfg.points)
    missing = sorted(set(tr.points_mm) - set(places))
    if missing:
        raise InputFileError(tr.path, f"no place on the skin for recorded point(s) {', '.join(missing)} "
                                      "(give them in [simulation.body.trace] points or the sidecar)")
    return places


def _signals(tr: Trace, cfg: BodyTraceConfig,
             ) -> tuple[FloatArray, FloatArray | None, dict[str, FloatArray] | None]:
    """(normalised breathing signal, tumour (N, 3) or None, skin point displacements or None)."""
    target = tr.target_mm
    if tr.surrogate is not None:
        raw = -tr.surrogate if cfg.invert_surrogate else tr.surrogate
        s, _, _ = normalise(np.asarray(raw, dtype=np.float64))
        return s, target, None
    if target is not None:
        proj, axis = principal_projection(target)
        if axis[1] > 0.0:          # inhale moves the target inferior (-y)
            proj = -proj
        s, _, _ = normalise(proj)
        return s, target, None
    if tr.points_mm:
        norm = []
        for name in sorted(tr.points_mm):
            proj, axis = principal_projection(tr.points_mm[name])
            norm.append(normalise(-proj if axis[2] < 0.0 else proj)[0])
        return np.mean(norm, axis=0), None, dict(tr.points_mm)
    raise ValueError("the trace holds no surrogate, tumour or skin point")


def traced_body(sim: SimulationConfig, phantom: BodyPhantom, motion: PatientMotion) -> DeformableBody:
    """The deformable body driven by the configured trace, read here (a bad trace is an
    :class:`hil.errors.InputFileError` naming it and what is wrong)."""
    cfg = sim.body.trace
    if cfg.path is None:
        raise ValueError("traced_body needs [simulation.body.trace] path")
    trace = read_trace(cfg.path, None if cfg.format == "auto" else cfg.format)
    return trace_body(sim, phantom, motion, trace)
