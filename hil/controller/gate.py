"""GATE: the hold-breath gate (seed 003 section 3, clinical step 4).

A reference marker state is recorded at registration (the patient holding breath). The gate
opens when the body is back in that state for ``dwell_s``: the RMS deviation of the live markers
from the reference under ``tolerance_mm``, no marker farther than ``marker_tolerance_mm`` from its
reference, and the shape back (the RMS residual of a rigid fit of the reference onto the live
markers under ``shape_tolerance_mm``: a body that deforms can bring the markers back on average
but not each of them). Any sample that fails a check (or without enough markers) restarts the
dwell. ``timeout_s`` after :meth:`BreathHoldGate.restart` without opening, the gate reports a
time-out (the controller goes back to waiting and says so). Like bluesky's suspenders the gate
gives a human-readable justification of its state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.controller.config import GateConfig
from hil.errors import GeometryError
from hil.geometry.registration import register_horn

FloatArray = NDArray[np.float64]

MIN_GATE_MARKERS = 3

#: what a pause's reason says when the body no longer matches the registration and the operator
#: should register again, not resume into the same pause (scripted operators read it too)
REREGISTER_ADVICE = "(re-register)"


def rms_deviation_mm(reference_mm: FloatArray, live_mm: FloatArray) -> tuple[float, int]:
    """RMS distance between corresponding reference and live markers, over the rows where both
    are finite (a missing live marker is a NaN row). Returns (rms_mm, markers_used); rms is inf
    when no marker is usable."""
    ok = np.all(np.isfinite(reference_mm), axis=1) & np.all(np.isfinite(live_mm), axis=1)
    n = int(ok.sum())
    if n == 0:
        return math.inf, 0
    d = np.linalg.norm(live_mm[ok] - reference_mm[ok], axis=1)
    return float(np.sqrt(np.mean(d * d))), n


@dataclass(frozen=True)
class GateMeasures:
    """How far the live markers are from the reference state: ``rms_mm`` (inf without markers),
    ``markers`` used, the largest single-marker distance ``max_marker_mm``, and the ``shape_mm``
    (RMS residual of the rigid fit reference -> live; inf with fewer than 3 markers), mm.
    ``deviations_mm`` holds each reference marker's distance from its reference position, in
    reference order (NaN where the marker is not seen; empty without live markers)."""

    rms_mm: float
    markers: int
    max_marker_mm: float
    shape_mm: float
    deviations_mm: tuple[float, ...] = ()

    def problem(self, cfg: GateConfig) -> str | None:
        """Why the body is not back in the reference state by ``cfg``'s tolerances (None: it is)."""
        if self.markers < MIN_GATE_MARKERS:
            return f"only {self.markers} reference markers seen (need {MIN_GATE_MARKERS})"
        if self.rms_mm > cfg.tolerance_mm:
            return (f"markers {self.rms_mm:.2f} mm RMS from the reference state "
                    f"(tolerance {cfg.tolerance_mm} mm)")
        marker_tol = 2.0 * cfg.tolerance_mm if cfg.marker_tolerance_mm is None else cfg.marker_tolerance_mm
        if self.max_marker_mm > marker_tol:
            return f"a marker {self.max_marker_mm:.2f} mm from its reference (tolerance {marker_tol} mm)"
        if cfg.shape_tolerance_mm is not None and self.shape_mm > cfg.shape_tolerance_mm:
            return (f"the body's shape {self.shape_mm:.2f} mm from the reference after removing a rigid "
                    f"motion (tolerance {cfg.shape_tolerance_mm} mm)")
        return None


def gate_measures(reference_mm: FloatArray, live_mm: FloatArray | None) -> GateMeasures:
    """:class:`GateMeasures` of the rows where both sets are finite (a missing live marker is a
    NaN row)."""
    if live_mm is None:
        return GateMeasures(math.inf, 0, math.inf, math.inf)
    live = np.asarray(live_mm, dtype=np.float64)
    ok = np.all(np.isfinite(reference_mm), axis=1) & np.all(np.isfinite(live), axis=1)
    n = int(ok.sum())
    every = np.full(len(ok), math.nan)
    if n == 0:
        return GateMeasures(math.inf, 0, math.inf, math.inf, tuple(every.tolist()))
    d = np.linalg.norm(live[ok] - reference_mm[ok], axis=1)
    every[ok] = d
    shape = math.inf
    if n >= MIN_GATE_MARKERS:
        try:
            shape = float(register_horn(live[ok], reference_mm[ok]).fre_rms_mm)
        except GeometryError:
            shape = math.inf
    return GateMeasures(float(np.sqrt(np.mean(d * d))), n, float(d.max()), shape, tuple(every.tolist()))


@dataclass(frozen=True)
class GateStatus:
    """One gate update: ``open``; the current ``deviation_rms_mm`` (inf without markers);
    ``dwell_s`` under tolerance so far; ``timed_out`` (only reported once per wait); the largest
    single-marker distance, the shape residual and each marker's distance (:class:`GateMeasures`)."""

    open: bool
    deviation_rms_mm: float
    markers: int
    dwell_s: float
    timed_out: bool
    justification: str
    max_marker_mm: float = math.inf
    shape_mm: float = math.inf
    deviations_mm: tuple[float, ...] = ()


class BreathHoldGate:
    """The gate. Feed it matched live markers (rows in reference order, NaN when not seen).

    Args:
        cfg: tolerance, dwell, timeout.
        reference_mm: (N, 3) the reference marker state (optical frame, mm).
    """

    def __init__(self, cfg: GateConfig, reference_mm: FloatArray) -> None:
        self.cfg = cfg
        self.reference_mm = np.asarray(reference_mm, dtype=np.float64)
        self._since_ns: int | None = None      # start of the current under-tolerance run
        self._wait_start_ns: int | None = None
        self._timed_out_reported = False

    def restart(self, now_ns: int) -> None:
        """Start (or restart) waiting: the timeout counts from ``now_ns``; the dwell restarts."""
        self._since_ns = None
        self._wait_start_ns = now_ns
        self._timed_out_reported = False

    def update(self, live_mm: FloatArray | None, t_ns: int) -> GateStatus:
        """Feed one sample taken at ``t_ns`` (None: no markers seen)."""
        if self._wait_start_ns is None:
            self.restart(t_ns)
        m = gate_measures(self.reference_mm, live_mm)
        rms, n = m.rms_mm, m.markers
        problem = m.problem(self.cfg)
        under = problem is None
        if under:
            if self._since_ns is None:
                self._since_ns = t_ns
            dwell = (t_ns - self._since_ns) * 1e-9
        else:
            self._since_ns = None
            dwell = 0.0
        is_open = under and dwell >= self.cfg.dwell_s
        assert self._wait_start_ns is not None
        waited = (t_ns - self._wait_start_ns) * 1e-9
        timed_out = False
        if not is_open and waited > self.cfg.timeout_s and not self._timed_out_reported:
            timed_out = True
            self._timed_out_reported = True
        if problem is not None:
            why = f"closed: {problem}"
        elif not is_open:
            why = f"settling: {rms:.2f} mm RMS for {dwell:.2f} s of {self.cfg.dwell_s} s"
        else:
            why = f"open: {rms:.2f} mm RMS for {dwell:.2f} s"
        if timed_out:
            why = (f"no breath-hold within {self.cfg.timeout_s} s ({why}); waiting again — "
                   f"ask the patient to hold breath")
        return GateStatus(is_open, rms, n, dwell, timed_out, why, m.max_marker_mm, m.shape_mm,
                          m.deviations_mm)


class MovedPatientWatch:
    """Tells a patient who moved on the table from one who is breathing (GATE and COMPENSATE).

    A shift within the correction bounds keeps the skin markers away from the registered state
    at every point of the breathing cycle while their shape is back; a breathing patient passes
    the reference at every end-exhale, a held breath lasts ``hold_request_s``. So: once the
    markers' RMS deviation has not come within ``tolerance_mm`` for ``moved_after_s`` (s) and
    the shape is back within ``shape_tolerance_mm`` (1 mm when that check is off), the patient
    has moved and the procedure needs a new registration. ``moved_after_s`` None: never judged.
    """

    def __init__(self, cfg: GateConfig) -> None:
        self.cfg = cfg
        self._last_within_ns: int | None = None

    def restart(self, t_ns: int) -> None:
        """Start watching at ``t_ns`` (controller clock): the markers count as within then."""
        self._last_within_ns = t_ns

    def update(self, rms_mm: float, markers: int, shape_mm: float, t_ns: int) -> str | None:
        """Feed one measurement at ``t_ns`` (the pair's exposure); returns why the patient looks
        moved (the operator's reason), or None."""
        g = self.cfg
        if self._last_within_ns is None or rms_mm <= g.tolerance_mm:
            self._last_within_ns = t_ns
            return None
        away_s = (t_ns - self._last_within_ns) * 1e-9
        if g.moved_after_s is None or away_s < g.moved_after_s or markers < MIN_GATE_MARKERS:
            return None
        shape_tol = 1.0 if g.shape_tolerance_mm is None else g.shape_tolerance_mm
        if not shape_mm <= shape_tol:
            return None
        return (f"the skin markers have stayed more than {g.tolerance_mm} mm RMS from the registered state "
                f"for {away_s:.0f} s (now {rms_mm:.1f} mm) with their shape back ({shape_mm:.2f} mm): "
                f"the patient has moved since registration {REREGISTER_ADVICE}")
