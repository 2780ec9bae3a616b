"""Identification and tracking of the skin and flange markers in each stereo pair.

Input: the marker centres the locator triangulated (optical frame, mm, any order). Output, in the
:class:`~hil.controller.estimate.Estimate`: the skin markers in CT-fiducial order (against the
registered reference once there is one, else against the plan's fiducial layout) and the flange
markers in layout order; NaN rows are markers not seen this pair. Once registered, the patient's
change (optical frame) is estimated by ``[procedure.compensation] estimator``
(:mod:`hil.controller.change_estimate`), its direction steered at the modelled target when
``target_model = "surrogate"`` (:mod:`hil.controller.target_model`), and fed to the motion filter.

Tracking first (each predicted marker takes the nearest point within ``TRACK_TOLERANCE_MM``); a
full identification against the layout when fewer than three markers are tracked. The skin and the
flange are updated by separate calls: the controller updates the flange after the pair's setpoint
is out unless the setpoint needs it (a bias correction).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from hil.controller.change_estimate import estimate_change
from hil.controller.cost import CostHistogram
from hil.controller.estimate import Estimate, count_seen
from hil.controller.registration import identify, track

FloatArray = NDArray[np.float64]
#: Frame-to-frame tracking gate (mm): a marker moves far less than this between pairs.
TRACK_TOLERANCE_MM = 6.0


class MarkerTracker:
    """Updates the estimate's marker sets from one pair's points.

    Args:
        match_tolerance_mm: identification tolerance against a layout (``registration``).
    """

    def __init__(self, match_tolerance_mm: float) -> None:
        self.match_tolerance_mm = match_tolerance_mm
        #: the change estimator's time per registered pair (``[procedure.compensation]
        #: estimator``), µs: what it adds to the pair path
        self.change_cost = CostHistogram()

    def update(self, est: Estimate, points_mm: FloatArray, exposure_t_ns: int,
               reference_hook: Callable[[], None] | None = None) -> None:
        """Identify/track ``points_mm`` (M, 3) into ``est``: :meth:`update_patient`, then
        :meth:`update_flange`. Never raises for missing markers: they are NaN rows."""
        self.update_patient(est, points_mm, exposure_t_ns, reference_hook)
        self.update_flange(est, points_mm)

    def update_patient(self, est: Estimate, points_mm: FloatArray, exposure_t_ns: int,
                       reference_hook: Callable[[], None] | None = None) -> None:
        """The skin markers of ``points_mm`` (M, 3) into ``est`` and, once registered, the
        patient's measured change, fed to the motion filter at ``exposure_t_ns``.
        ``reference_hook`` runs after the change is measured and before it is filtered (the
        reference sensor may stand in for it). The flange markers are left for
        :meth:`update_flange` (independent of these: each tracks its own previous set)."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        tol = self.match_tolerance_mm
        if est.patient_reg is None:
            est.live_mm = identify(pts, est.plan.fiducials_mm, tol)
            return
        ref = est.patient_reg.reference_optical_mm
        prev = est.live_mm
        predicted = ref if prev is None else np.where(np.isfinite(prev), prev, ref)
        live = track(pts, predicted, TRACK_TOLERANCE_MM)
        if count_seen(live) < 3:
            found = identify(pts, np.nan_to_num(ref), tol)
            live = found if found is not None else live
        est.live_mm = live
        c = est.comp_cfg
        t0 = time.perf_counter_ns()   # the estimator's cost (hil/controller/cost.py), not control
        fit = estimate_change(ref, live, est.T_center.t, c.estimator, c.weight_sigma_mm, est.entry_rows)
        change = None if fit is None else fit.T_live_from_ref
        est.target_steer = None
        if change is not None and est.target_tracker is not None:
            T_oi = est.patient_reg.T_optical_from_image
            measured = (None if est.target_sensor is None
                        else est.target_sensor.target_at(exposure_t_ns, change.R @ T_oi.R))
            est.target_steer = est.target_tracker.steer(change, ref, live, est.plan, T_oi, exposure_t_ns,
                                                        measured)
            change = est.target_steer.T_live_from_ref
        fit_ns = time.perf_counter_ns() - t0
        self.change_cost.add_ns(fit_ns)
        est.change_fit_cost = (exposure_t_ns, fit_ns)
        est.change_fit = fit
        est.T_change_meas = change
        est.change_t_ns = None if change is None else exposure_t_ns
        if reference_hook is not None:
            reference_hook()
        if est.T_change_meas is not None:
            est.filter.update_about(est.T_change_meas, est.T_center, exposure_t_ns)

    def update_flange(self, est: Estimate, points_mm: FloatArray) -> None:
        """The flange markers of ``points_mm`` (M, 3) into ``est`` (layout order; a new array,
        which :meth:`Estimate.T_optical_from_tcp_measured` keys its registration on)."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        tol = self.match_tolerance_mm
        layout = est.rig.flange_markers_tcp_mm
        if est.flange_mm is not None and count_seen(est.flange_mm) >= 3:
            fl = track(pts, est.flange_mm, TRACK_TOLERANCE_MM)
            if count_seen(fl) < 3:
                fl2 = identify(pts, layout, tol)
                fl = fl2 if fl2 is not None else fl
        else:
            fl2 = identify(pts, layout, tol)
            fl = fl2 if fl2 is not None else np.full(layout.shape, np.nan)
        est.flange_mm = fl


class FlangeUpdate:
    """One pair's :meth:`MarkerTracker.update_flange`, run by the first call only: the setpoint's
    command calls it when it needs the flange (a bias correction), the tick once the setpoint
    is out."""

    __slots__ = ("_est", "_points_mm", "_tracker", "done")

    def __init__(self, tracker: MarkerTracker, est: Estimate, points_mm: FloatArray) -> None:
        self._tracker, self._est, self._points_mm = tracker, est, points_mm
        self.done = False

    def __call__(self) -> None:
        if not self.done:
            self.done = True
            self._tracker.update_flange(self._est, self._points_mm)
