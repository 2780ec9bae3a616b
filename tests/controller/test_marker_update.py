"""The marker update in two calls (hil/controller/markers.py): the skin markers and the patient's
change (``update_patient``) and the flange markers (``update_flange``) give what one ``update``
gives, in either order, and a pair's :class:`FlangeUpdate` runs once however often it is called."""

from __future__ import annotations

import numpy as np
import pytest

from hil.controller.config import ProcedureConfig
from hil.controller.estimate import Estimate, count_seen
from hil.controller.markers import FlangeUpdate, MarkerTracker
from hil.controller.plan_file import load_plan
from hil.controller.planning import RigGeometry
from hil.controller.registration import PatientRegistration
from hil.geometry.transform import RigidTransform

PLAN = load_plan("configs/plans/sim_plan.json")
FLANGE_MM = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 25.0, 0.0], [-30.0, -20.0, 0.0]])
RIG = RigGeometry(RigidTransform.identity(), FLANGE_MM)
T_OPTICAL_FROM_IMAGE = RigidTransform.from_rotvec((0.0, 0.1, 0.0), (0.0, 0.0, 600.0))
FLANGE_AT = RigidTransform.from_rotvec((0.2, 0.0, 0.1), (50.0, -300.0, 550.0))


def _estimate(registered: bool) -> Estimate:
    est = Estimate(PLAN, RIG, ProcedureConfig())
    if registered:
        ref = T_OPTICAL_FROM_IMAGE.apply(PLAN.fiducials_mm)
        est.patient_reg = PatientRegistration(T_OPTICAL_FROM_IMAGE, 0.05, 0.1, ref, len(ref), 10)
        est.live_mm = ref.copy()
    return est


def _points(shift_mm: float) -> np.ndarray:
    """The skin markers moved by ``shift_mm`` along x, then the flange markers, shuffled."""
    skin = T_OPTICAL_FROM_IMAGE.apply(PLAN.fiducials_mm) + np.array([shift_mm, 0.0, 0.0])
    pts = np.vstack([skin, FLANGE_AT.apply(FLANGE_MM)])
    return pts[np.random.default_rng(7).permutation(len(pts))]


@pytest.mark.parametrize("registered", [False, True])
def test_the_two_calls_give_what_one_update_gives(registered: bool) -> None:
    tracker = MarkerTracker(match_tolerance_mm=1.0)
    whole, patient_first, flange_first = (_estimate(registered) for _ in range(3))
    for k, shift in enumerate((0.0, 0.5, 1.0)):
        pts, t_ns = _points(shift), 1_000_000_000 + k * 33_000_000
        tracker.update(whole, pts, t_ns)
        tracker.update_patient(patient_first, pts, t_ns)
        tracker.update_flange(patient_first, pts)
        tracker.update_flange(flange_first, pts)
        tracker.update_patient(flange_first, pts, t_ns)
    assert whole.flange_mm is not None
    assert np.isfinite(whole.flange_mm).all()   # every flange marker found
    np.testing.assert_allclose(whole.flange_mm, FLANGE_AT.apply(FLANGE_MM), rtol=0, atol=1e-9)
    for est in (patient_first, flange_first):
        assert est.live_mm is not None
        assert whole.live_mm is not None
        assert est.live_mm.tolist() == whole.live_mm.tolist()
        assert est.flange_mm is not None
        assert est.flange_mm.tolist() == whole.flange_mm.tolist()
        if registered:
            x, v = est.filter.vectors()
            xw, vw = whole.filter.vectors()
            assert x.tolist() == xw.tolist()
            assert v.tolist() == vw.tolist()
    if registered:
        assert whole.T_change_meas is not None
        np.testing.assert_allclose(whole.T_change_meas.t, [1.0, 0.0, 0.0], rtol=0, atol=1e-9)


def test_a_pairs_flange_update_runs_once() -> None:
    calls: list[int] = []

    class Counting(MarkerTracker):
        def update_flange(self, est: Estimate, points_mm: np.ndarray) -> None:
            calls.append(len(points_mm))
            super().update_flange(est, points_mm)

    est = _estimate(registered=False)
    pts = _points(0.0)
    once = FlangeUpdate(Counting(match_tolerance_mm=1.0), est, pts)
    assert est.flange_mm is None   # nothing runs before the first call
    once()
    once()
    assert once.done
    assert calls == [len(pts)]
    assert count_seen(est.flange_mm) == len(FLANGE_MM)   # the pair's flange markers are in
