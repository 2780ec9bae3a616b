"""GATE: the hold-breath gate (seed 003 section 3, clinical step 4).

A reference marker state is recorded at registration (the patient holding breath). The gate
opens when the RMS deviation of the live markers from that reference stays under
``tolerance_mm`` for ``dwell_s``; any sample over tolerance (or without enough markers) restarts
the dwell. ``timeout_s`` after :meth:`BreathHoldGate.restart` without opening, the gate reports a
time-out (the controller goes back to waiting and says so). Like bluesky's suspenders the gate
gives a human-readable justification of its state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil.controller.config import GateConfig

FloatArray = NDArray[np.float64]

MIN_GATE_MARKERS = 3


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
class GateStatus:
    """One gate update: ``open``; the current ``deviation_rms_mm`` (inf without markers);
    ``dwell_s`` under tolerance so far; ``timed_out`` (only reported once per wait)."""

    open: bool
    deviation_rms_mm: float
    markers: int
    dwell_s: float
    timed_out: bool
    justification: str


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
        if live_mm is None:
            rms, n = math.inf, 0
        else:
            rms, n = rms_deviation_mm(self.reference_mm, np.asarray(live_mm, dtype=np.float64))
        under = n >= MIN_GATE_MARKERS and rms <= self.cfg.tolerance_mm
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
        if n < MIN_GATE_MARKERS:
            why = f"closed: only {n} reference markers seen (need {MIN_GATE_MARKERS})"
        elif not under:
            why = (f"closed: markers {rms:.2f} mm RMS from the reference state "
                   f"(tolerance {self.cfg.tolerance_mm} mm)")
        elif not is_open:
            why = f"settling: {rms:.2f} mm RMS for {dwell:.2f} s of {self.cfg.dwell_s} s"
        else:
            why = f"open: {rms:.2f} mm RMS for {dwell:.2f} s"
        if timed_out:
            why = (f"no breath-hold within {self.cfg.timeout_s} s ({why}); waiting again — "
                   f"ask the patient to hold breath")
        return GateStatus(is_open, rms, n, dwell, timed_out, why)
