"""A sensor at the target (``[procedure.tracking] target_sensor``, issue 41): the target measured
during the procedure rather than modelled from the skin.

Why: the surrogate target model (:mod:`hil.controller.target_model`) predicts the target from the
skin. On the recorded tumour traces the skin does not carry all of the tumour's motion: even a
correlation model refitted live to the true target at every pair leaves 4 of 12 traces over 1 mm
following error p95, where the true target leaves 1 (docs/benchmarks.md, seventeenth session).
Clinical systems close that gap by measuring the target during treatment: X-ray images of
implanted fiducials (CyberKnife Synchrony), implanted electromagnetic transponders (Calypso), an
EM-tracked instrument at the lesion (electromagnetic navigation). This is the EM kind, through the
project's magnetic tracker.

**The measurement.** The sensor is fixed at (or near) the tumour; ``target_sensor_offset_mm`` is
where it sits against the planned target in the planning CT (image frame: its position in the CT
less the target's). Each tracker read adds the sensor's sample to a short history, in the optical
frame through the tracker registration ``T_optical_from_tracker``. A pair's target is the sensor's
position at the pair's exposure less the offset turned as the patient is now:

    ``target_optical = p_sensor(t_exposure) - R_now offset``,  ``R_now = R_change R_optical_from_image``

``p_sensor(t)`` linear between the two samples around ``t`` when they are at most
``target_sensor_max_age_ms`` apart, else the nearest sample within that of ``t``; else there is no
measurement for the pair and it falls back to the surrogate model (:class:`TargetReading` says why).

**What it assumes, where it fails**: the sensor moves with the target (fixed to it; a sensor that
slips in the tissue moves the target with it); the tracker registration is right (its error passes
into the target one to one: ``hil tracker-calibrate``); the tracker's stamps are on the camera's
clock (``[calibration] rig`` time offsets; a 20 ms offset at 20 mm/s breathing is 0.4 mm); the field
is undistorted near the target (metal near the field bends it; the samples' quality figure is not
judged here, as nowhere in the controller yet). It sees what no skin model sees: the target's own
motion, its drift, where a breath-hold leaves it. Not thread-safe: the controller's thread.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.tracker import TrackerSample
from hil.geometry.transform import RigidTransform

FloatArray = NDArray[np.float64]

__all__ = ["HISTORY_S", "HISTORY_SAMPLES", "TargetReading", "TargetSensor"]

#: samples are kept this long behind the newest, s (several camera latencies)
HISTORY_S = 1.0
#: and at most this many (a tracker at 250 Hz fills a second)
HISTORY_SAMPLES = 256
_HISTORY_NS = round(HISTORY_S * 1e9)


@dataclass(frozen=True)
class TargetReading:
    """The sensor's target for one pair.

    Attributes:
        target_optical_mm: (3,) the measured target, optical frame, mm (None: no measurement).
        why_not: why there is none ("" when there is).
    """

    target_optical_mm: FloatArray | None
    why_not: str = ""


class TargetSensor:
    """The target sensor's recent samples and the target they give (module doc).

    Args:
        name: the sensor's name as the tracker reports it.
        offset_image_mm: (3,) the sensor less the planned target in the planning CT, image frame, mm.
        max_age_s: ``target_sensor_max_age_ms`` in seconds.
        T_optical_from_tracker: the tracker registration (mm).
    """

    def __init__(self, name: str, offset_image_mm: FloatArray, max_age_s: float,
                 T_optical_from_tracker: RigidTransform) -> None:
        self.name = name
        self.offset_image_mm = np.asarray(offset_image_mm, dtype=np.float64).reshape(3)
        self.max_age_ns = round(max_age_s * 1e9)
        self.T_optical_from_tracker = T_optical_from_tracker
        #: (stamp ns, position optical mm), oldest first, within :data:`HISTORY_S` of the newest
        self._history: deque[tuple[int, FloatArray]] = deque(maxlen=HISTORY_SAMPLES)

    def add(self, samples: Mapping[str, TrackerSample]) -> None:
        """Keep the sensor's sample of a tracker read (once: a sample no newer than the last kept
        is the same one read again; the history keeps :data:`HISTORY_S` behind the newest). A
        missing sample or one without a finite pose is not kept: it shows as a gap around the pairs
        it would have served."""
        s = samples.get(self.name)
        if s is None or s.missing or s.T_tracker_from_sensor is None:
            return
        if self._history and s.t_ns <= self._history[-1][0]:
            return
        p = self.T_optical_from_tracker.apply(s.T_tracker_from_sensor.t).reshape(3)
        if np.isfinite(p).all():
            hist = self._history
            hist.append((s.t_ns, p))
            while s.t_ns - hist[0][0] > _HISTORY_NS:
                hist.popleft()

    def position_at(self, t_ns: int) -> TargetReading:
        """The sensor's position at ``t_ns`` (controller clock), optical frame (module doc), or why
        there is none."""
        hist = self._history
        if not hist:
            return TargetReading(None, f"no sample of the target sensor {self.name!r} yet")
        after = next((i for i in range(len(hist)) if hist[i][0] > t_ns), None)
        before = len(hist) - 1 if after is None else after - 1
        if before >= 0 and after is not None:
            (ta, pa), (tb, pb) = hist[before], hist[after]
            if tb - ta <= self.max_age_ns:
                f = (t_ns - ta) / (tb - ta)
                p: FloatArray = pa + f * (pb - pa)
                return TargetReading(p)
        near = min((i for i in (before, after) if i is not None and i >= 0),
                   key=lambda i: abs(hist[i][0] - t_ns))
        gap_ns = abs(hist[near][0] - t_ns)
        if gap_ns <= self.max_age_ns:
            return TargetReading(hist[near][1].copy())
        return TargetReading(None, f"the target sensor's nearest sample is {gap_ns * 1e-6:.0f} ms from the "
                                   f"pair's exposure (bound {self.max_age_ns * 1e-6:.0f} ms)")

    def target_at(self, t_ns: int, R_optical_from_image_now: FloatArray) -> TargetReading:
        """The measured target at ``t_ns``: the sensor's position less its offset turned by
        ``R_optical_from_image_now`` (3x3, the patient's orientation now), optical frame, mm."""
        got = self.position_at(t_ns)
        if got.target_optical_mm is None:
            return got
        R_now = np.asarray(R_optical_from_image_now, dtype=np.float64)
        target: FloatArray = got.target_optical_mm - R_now @ self.offset_image_mm
        if not all(math.isfinite(x) for x in target.tolist()):
            return TargetReading(None, "the target sensor's position is not finite")
        return TargetReading(target)
