"""Patient faults played by the simulated body: a cough, a shift on the table, a skin marker lost
or moved (``[[faults]]`` of device ``"patient"``, :mod:`hil.config.faults`; issue 41's "Bad input
and faults").

Each acts on the body before its rigid part (image frame at rest: x lateral, y superior, z
anterior, mm), on the rigid phantom and the deformable body alike, over the fault's window
``start_s <= t < start_s + duration_s`` of world time (s since the world was built):

- ``cough``: a non-rigid jolt. Every body point moves ``offset_mm`` scaled by a raised-cosine bump
  over the window (0 at its ends, 1 at its middle) and by a weight that grows superior-wards
  (:func:`cough_weight`: 0.4 at 100 mm inferior of the entry, 1.0 at 50 mm superior of it), so
  the markers do not move as one body. The target takes the weight at the entry.
- ``patient_shift``: the whole body translates by ``offset_mm``, ramped smoothly (raised
  cosine) over the window and kept after it (the patient moved and stays moved).
- ``marker_lost``: the skin markers ``markers`` are not rendered during the window.
- ``marker_moved``: the skin markers ``markers`` slide ``offset_mm`` over the skin during the window
  (raised-cosine ramp) and stay there: tape peeling, a marker pressed back elsewhere. A slide the
  tracker can follow from frame to frame is the dangerous case (a marker that jumps further
  than the tracking tolerance is simply lost to the controller): the registered layout no longer
  matches the skin.

Marker indices beyond the phantom's markers are ignored (the config cannot know the count).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from drivers.sim.body import BodyState
from hil.config.faults import FaultKind, FaultSpec

FloatArray = NDArray[np.float64]

#: Cough weight: from COUGH_WEIGHT_MIN at COUGH_WEIGHT_SPAN_MM[0] to 1 at [1] (mm superior of the entry).
COUGH_WEIGHT_MIN = 0.4
COUGH_WEIGHT_SPAN_MM = (-100.0, 50.0)


def bump(t_s: float, start_s: float, duration_s: float) -> float:
    """Raised cosine over the window: 0 outside it and at its ends, 1 at its middle."""
    u = (t_s - start_s) / duration_s
    if not 0.0 <= u < 1.0:
        return 0.0
    return 0.5 * (1.0 - math.cos(2.0 * math.pi * u))


def ramp(t_s: float, start_s: float, duration_s: float) -> float:
    """Smooth step over the window: 0 before it, 1 after it (half a raised cosine)."""
    u = (t_s - start_s) / duration_s
    if u <= 0.0:
        return 0.0
    if u >= 1.0:
        return 1.0
    return 0.5 * (1.0 - math.cos(math.pi * u))


def cough_weight(y_mm: FloatArray, entry_y_mm: float) -> FloatArray:
    """How much of a cough's offset a point at superior coordinate ``y_mm`` takes (module doc)."""
    lo, hi = COUGH_WEIGHT_SPAN_MM
    u = np.clip((np.asarray(y_mm, dtype=np.float64) - entry_y_mm - lo) / (hi - lo), 0.0, 1.0)
    out: FloatArray = COUGH_WEIGHT_MIN + (1.0 - COUGH_WEIGHT_MIN) * u
    return out


class PatientFaults:
    """The patient faults of a schedule (other devices' faults are ignored).

    Args:
        faults: the setup's ``[[faults]]``.
        entry_rest_mm: the entry at rest (image frame, mm): the cough weight's origin.
    """

    def __init__(self, faults: Sequence[FaultSpec], entry_rest_mm: FloatArray) -> None:
        self.faults = tuple(f for f in faults if f.device == "patient")
        self.entry_y_mm = float(np.asarray(entry_rest_mm, dtype=np.float64)[1])

    def __bool__(self) -> bool:
        return bool(self.faults)

    def apply(self, t_s: float, state: BodyState) -> BodyState:
        """The body at world time ``t_s`` with the faults acting (image frame at rest, mm).
        Normals are kept (every offset here is a translation of the points)."""
        markers, entry, target = state.markers_mm.copy(), state.entry_mm.copy(), state.target_mm.copy()
        for f in self.faults:
            off = np.asarray(f.patient_offset_mm, dtype=np.float64)
            if f.kind is FaultKind.COUGH:
                b = bump(t_s, f.start_s, f.duration_s)
                if b > 0.0:
                    markers += b * cough_weight(markers[:, 1], self.entry_y_mm)[:, None] * off
                    w_entry = float(cough_weight(np.array([entry[1]]), self.entry_y_mm)[0])
                    entry += b * w_entry * off
                    target += b * w_entry * off
            elif f.kind is FaultKind.PATIENT_SHIFT:
                r = ramp(t_s, f.start_s, f.duration_s)
                markers += r * off
                entry += r * off
                target += r * off
            elif f.kind is FaultKind.MARKER_MOVED:
                r = ramp(t_s, f.start_s, f.duration_s)
                for i in f.markers:
                    if i < len(markers):
                        markers[i] += r * off
        return replace(state, markers_mm=markers, entry_mm=entry, target_mm=target)

    def lost(self, t_s: float) -> frozenset[int]:
        """Skin marker indices not rendered at world time ``t_s``."""
        out: set[int] = set()
        for f in self.faults:
            if f.kind is FaultKind.MARKER_LOST and f.active(t_s):
                out.update(f.markers)
        return frozenset(out)
