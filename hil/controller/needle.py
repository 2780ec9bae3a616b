"""The optical needle-axis check (seed 004) as the procedure uses it: before LOCK (when required)
and while locked (the alarm), against the planned path as the patient is seen now.

Records ``needle_axis_measured`` / ``needle_axis_unavailable`` per measurement and
``needle_check_refused`` when it holds LOCK back; keeps the direction errors for the summary.
"""

from __future__ import annotations

import collections
from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoFrame
from hil.controller import events as ev
from hil.controller.config import NeedleCheckConfig
from hil.controller.estimate import Estimate
from hil.controller.fsm import State
from hil.errors import HilError
from hil.geometry.collinear import PathError
from hil.session.log import SessionLog

FloatArray = NDArray[np.float64]


class NeedleAxisMeasurement(Protocol):
    """What the procedure needs of a needle-axis measurement (cylinder contours,
    :class:`hil.vision.lines.NeedleAxisMeasurement`, or collinear beads,
    :class:`hil.vision.beads.BeadAxisMeasurement`): its error against the path."""

    @property
    def path_error(self) -> PathError: ...


#: Needle-axis check (seed 004 §III): (frame, expected visible segment start, end, entry, target;
#: optical frame, mm) -> the measured axis and its error against the path. Raises HilError
#: (VisionError, DegenerateConfigurationError) when the needle cannot be measured.
NeedleAxisChecker = Callable[[StereoFrame, FloatArray, FloatArray, FloatArray, FloatArray],
                             NeedleAxisMeasurement]


class NeedleAlarmWindow:
    """The needle alarm's judgement while locked: over the last ``readings`` needle-axis readings
    (measured ones only: a frame where the needle is not measured neither counts nor resets), the
    axis is out of bounds when more than half of them are (a majority vote).

    So a single outlier reading is never an alarm (``readings`` >= 3), and a deviation that stays
    is one at its :attr:`needed`-th consecutive reading (``readings // 2 + 1``; with readings at
    the camera's rate f, that many frame periods after the deviation is first read). The window
    starts empty at each LOCK.
    """

    def __init__(self, readings: int) -> None:
        if readings < 1:
            raise ValueError(f"an alarm window needs at least one reading, got {readings}")
        self.readings = readings
        self._out: collections.deque[bool] = collections.deque(maxlen=readings)

    @property
    def needed(self) -> int:
        """Out-of-bounds readings in the window that raise the alarm."""
        return self.readings // 2 + 1

    @property
    def out_of_bounds(self) -> int:
        """Out-of-bounds readings among the last :attr:`readings`."""
        return sum(self._out)

    def add(self, out_of_bounds: bool) -> bool:
        """Take one reading; True when the window now judges the axis out of bounds."""
        self._out.append(out_of_bounds)
        return self.out_of_bounds >= self.needed


class NeedleCheck:
    """Applies ``lock.needle_check`` with ``checker`` (None: the check is never made)."""

    def __init__(self, cfg: NeedleCheckConfig | None, checker: NeedleAxisChecker | None,
                 session: SessionLog) -> None:
        self.cfg, self.checker, self.session = cfg, checker, session
        self.errors_deg: list[tuple[str, float]] = []   # (state, direction error) per measurement

    def measure(self, est: Estimate, frame: StereoFrame, state: State) -> NeedleAxisMeasurement | None:
        """Measure the needle axis on ``frame`` against the planned path as the patient is seen now
        (plan -> optical with the patient registration, then the measured change). None when the
        check is off, cannot be set up, or the needle is not measured (each logged)."""
        nc = self.cfg
        if nc is None or self.checker is None:
            return None
        if est.patient_reg is None or est.T_change_meas is None:
            self.session.write(ev.NEEDLE_AXIS_UNAVAILABLE, state=state,
                               reason="no patient registration or no live skin markers")
            return None
        T = est.T_change_meas @ est.patient_reg.T_optical_from_image
        entry = T.apply(est.plan.entry_mm).reshape(3)
        target = T.apply(est.plan.target_mm).reshape(3)
        u = (target - entry) / np.linalg.norm(target - entry)
        start, end = entry - nc.visible_to_mm * u, entry - nc.visible_from_mm * u
        try:
            m = self.checker(frame, start, end, entry, target)
        except HilError as exc:
            self.session.write(ev.NEEDLE_AXIS_UNAVAILABLE, state=state, frame_seq=frame.left.seq,
                               reason=f"{type(exc).__name__}: {exc}")
            return None
        pe = m.path_error
        self.errors_deg.append((state.value, pe.direction_error_deg))
        self.session.write(ev.NEEDLE_AXIS_MEASURED, state=state, frame_seq=frame.left.seq,
                           direction_error_deg=pe.direction_error_deg, entry_offset_mm=pe.entry_offset_mm,
                           target_offset_mm=pe.target_offset_mm,
                           within=pe.within(nc.max_direction_deg, nc.max_offset_mm))
        return m

    def ok_for_lock(self, est: Estimate, frame: StereoFrame, state: State) -> bool:
        """Before LOCK: True unless ``required_before_lock`` and the needle axis is not measured
        or out of bounds (then ``needle_check_refused`` is logged with the reason)."""
        nc = self.cfg
        if nc is None or not nc.required_before_lock:
            return True
        if self.checker is None:
            reason = "needle check required but no needle checker (camera model) is configured"
            self.session.write(ev.NEEDLE_CHECK_REFUSED, reason=reason)
            return False
        m = self.measure(est, frame, state)
        if m is None:
            self.session.write(ev.NEEDLE_CHECK_REFUSED, reason="needle axis not measured in this frame")
            return False
        pe = m.path_error
        if not pe.within(nc.max_direction_deg, nc.max_offset_mm):
            reason = (f"needle axis {pe.direction_error_deg:.2f} deg / entry {pe.entry_offset_mm:.2f} mm / "
                      f"target {pe.target_offset_mm:.2f} mm off the plan "
                      f"(limits {nc.max_direction_deg} deg, {nc.max_offset_mm} mm)")
            self.session.write(ev.NEEDLE_CHECK_REFUSED, reason=reason,
                               direction_error_deg=pe.direction_error_deg, entry_offset_mm=pe.entry_offset_mm,
                               target_offset_mm=pe.target_offset_mm)
            return False
        return True

    def summary_deg(self) -> float | None:
        """The direction error for the summary: the first measurement while locked, else the last
        one made (before LOCK), else None."""
        locked = [e for s, e in self.errors_deg if s == State.LOCK.value]
        if locked:
            return locked[0]
        return self.errors_deg[-1][1] if self.errors_deg else None
