"""The loop's predictor (``[procedure.compensation] predictor``) through the compensation path:
the filter feeds it the entry's measured displacement at each pair, COMPENSATE's setpoint is the
secant of its prediction (hil/controller/phases/predicted.py), and at a patient shift, a cough, a
breath-hold onset and a marker dropout it stays bounded, detects, falls back to alpha-beta and
says so. Scripted motion at 15 Hz, no simulator (docs/prediction.md "In the loop")."""

from __future__ import annotations

import math
import typing

import numpy as np
import pytest

from hil.controller.compensation import ChangePredictor
from hil.controller.config import CompensationConfig, ProcedureConfig
from hil.controller.estimate import Estimate
from hil.controller.parts import _predictor_fields
from hil.controller.phases.predicted import predicted_setpoint
from hil.controller.plan_file import load_plan
from hil.controller.planning import RigGeometry
from hil.errors import ConfigError
from hil.geometry import native
from hil.geometry.transform import RigidTransform
from hil.prediction import PREDICTOR_NAMES
from tests.controller.fakes import chain_estimate

RATE_HZ = 15.0
PERIOD_NS = round(1e9 / RATE_HZ)
T0_NS = 1_000_000_000
ENTRY_MM = np.array([10.0, -20.0, 300.0])
DIRECTION = np.array([0.0, 0.3, 1.0]) / math.hypot(0.3, 1.0)
LEAD_S = 0.031           # half a 500 Hz period + the 30 ms actuation lag
LATENCY_S = 0.060        # exposure -> setpoint
MAX_H_S = 0.15


def _breathing_mm(t_s: float) -> np.ndarray:
    return 10.0 * math.cos(math.pi * ((t_s % 4.0) / 4.0 - 0.5)) ** 4 * DIRECTION


def _estimate(name: str = "ar-ls") -> Estimate:
    est = chain_estimate(RigidTransform.identity(), RigidTransform.identity(),
                         RigidTransform.from_translation(ENTRY_MM), RigidTransform.identity())
    est.filter.predictor = ChangePredictor(CompensationConfig(predictor=name), RATE_HZ)   # type: ignore[arg-type]
    return est


def _feed(est: Estimate, k: int, x_mm: np.ndarray) -> int:
    """Pair ``k``'s measured change (a translation of the entry by ``x_mm``); its exposure, ns."""
    t_ns = T0_NS + k * PERIOD_NS
    est.filter.update_about(RigidTransform.from_translation(x_mm), est.T_center, t_ns)
    return t_ns


def _setpoint(est: Estimate, t_ns: int) -> tuple[RigidTransform, np.ndarray, np.ndarray] | None:
    return predicted_setpoint(est, t_ns, t_ns + round(LATENCY_S * 1e9), LEAD_S, MAX_H_S)


def _horizons() -> tuple[float, float]:
    h_a = LATENCY_S + LEAD_S
    return h_a, min(h_a + 1.0 / RATE_HZ, MAX_H_S)


def _line_mm(sp: tuple[RigidTransform, np.ndarray, np.ndarray], h_s: float) -> np.ndarray:
    """Where the servo loop's straight line puts the TCP at horizon ``h_s`` (chain: identity, so
    the TCP's translation is the entry's displacement)."""
    D0, v, _ = sp
    return typing.cast(np.ndarray, D0.t + v * h_s)


def _assert_bounded(sp: tuple[RigidTransform, np.ndarray, np.ndarray] | None, x_mm: np.ndarray) -> None:
    """The line at both horizons departs from the last measured displacement by at most the
    guard's bound min(5 mm, 60 mm/s x h)."""
    if sp is None:
        return
    for h in _horizons():
        assert float(np.linalg.norm(_line_mm(sp, h) - x_mm)) <= min(5.0, 60.0 * h) + 1e-9


def _warm(est: Estimate, n: int = 150) -> int:
    for k in range(n):
        _feed(est, k, _breathing_mm(k / RATE_HZ))
    return n


def test_the_setpoint_is_the_secant_of_the_prediction() -> None:
    est = _estimate()
    n = _warm(est)
    cp = est.filter.predictor
    assert cp is not None
    assert cp.predicting
    t_ns = T0_NS + (n - 1) * PERIOD_NS
    sp = _setpoint(est, t_ns)
    assert sp is not None
    for h in _horizons():
        np.testing.assert_allclose(_line_mm(sp, h), cp.predict_mm(h), rtol=0, atol=1e-9)
    np.testing.assert_allclose(sp[2], np.zeros(3), rtol=0, atol=1e-12)   # no rotation fed
    assert cp.fallbacks == 0
    assert cp.unreported == []


def test_the_prediction_beats_the_filter_line_on_breathing() -> None:
    """Over two breaths after warm-up, the predicted setpoint's error at the loop's horizons is
    below the alpha-beta filter's straight line (the reason it is in the loop)."""
    est = _estimate()
    n = _warm(est)
    err_pred, err_ab = [], []
    for k in range(n, n + 120):
        t_ns = _feed(est, k, _breathing_mm(k / RATE_HZ))
        sp = _setpoint(est, t_ns)
        assert sp is not None
        ab = est.tracking_setpoint(t_ns, MAX_H_S, 0.01)
        for h in _horizons():
            truth = _breathing_mm(k / RATE_HZ + h)
            err_pred.append(float(np.linalg.norm(_line_mm(sp, h) - truth)))
            err_ab.append(float(np.linalg.norm(ab[0].t + ab[1] * h - truth)))
    assert math.sqrt(np.mean(np.square(err_pred))) < 0.5 * math.sqrt(np.mean(np.square(err_ab)))


@pytest.mark.parametrize("name", ["ar-ls", "fast-lane", "wlms", "kalman-osc"])
def test_patient_shift_is_detected_said_and_bounded(name: str) -> None:
    est = _estimate(name)
    n = _warm(est, 200)
    cp = est.filter.predictor
    assert cp is not None
    assert cp.predicting
    shift = np.array([4.0, 0.0, 0.0])
    for k in range(n, n + 30):
        x = _breathing_mm(k / RATE_HZ) + shift
        t_ns = _feed(est, k, x)
        sp = _setpoint(est, t_ns)
        _assert_bounded(sp, x)
        if k < n + 15:   # the hold: 1 s of alpha-beta after the fallback
            assert sp is None
    assert cp.fallbacks == 1
    assert [f.exposure_t_ns for f in cp.unreported] == [T0_NS + n * PERIOD_NS]
    assert cp.unreported[0].reason.startswith("innovation ")
    assert cp.unreported[0].reason.endswith(" mm > 2 mm")
    fields = _predictor_fields(est)
    assert fields["predictor"] == name
    assert fields["predictor_fallbacks"] == 1
    assert fields["predictor_fallback_reason"] == cp.unreported[0].reason


def test_cough_spike_is_detected_and_bounded() -> None:
    est = _estimate()
    n = _warm(est)
    cp = est.filter.predictor
    assert cp is not None
    for k in range(n, n + 40):
        x = _breathing_mm(k / RATE_HZ) + (np.array([0.0, 0.0, 8.0]) if k == n else 0.0)
        t_ns = _feed(est, k, x)
        _assert_bounded(_setpoint(est, t_ns), x)
    assert cp.fallbacks == 1
    assert cp.unreported[0].exposure_t_ns == T0_NS + n * PERIOD_NS
    assert cp.unreported[0].reason.startswith("innovation ")


def test_breath_hold_onset_stays_bounded_and_comes_to_rest() -> None:
    """Breathing stops mid-exhale (the fastest point) and the body holds still: every setpoint is
    within the bound, and half a second into the hold the line is the held position."""
    est = _estimate()
    n = _warm(est, 151)   # pair 150 is at t = 10 s: mid-way down from the peak at 8 s
    held = _breathing_mm((n - 1) / RATE_HZ)
    for k in range(n, n + 30):
        t_ns = _feed(est, k, held)
        sp = _setpoint(est, t_ns)
        _assert_bounded(sp, held)
        if k >= n + 8 and sp is not None:
            for h in _horizons():
                np.testing.assert_allclose(_line_mm(sp, h), held, rtol=0, atol=1e-6)


def test_dropout_does_not_feed_the_predictor() -> None:
    est = _estimate()
    n = _warm(est)
    cp = est.filter.predictor
    assert cp is not None
    last_ns = T0_NS + (n - 1) * PERIOD_NS
    # pairs n .. n+5: the markers are not seen (no change measured: nothing is fed)
    assert cp.last_t_ns == last_ns
    dropped_ns = T0_NS + (n + 2) * PERIOD_NS
    assert _setpoint(est, dropped_ns) is None   # not this pair's sample: alpha-beta's setpoint
    t_ns = _feed(est, n + 6, _breathing_mm((n + 6) / RATE_HZ))
    assert cp.last_t_ns == t_ns
    assert cp.fallbacks == 1
    assert cp.unreported[0].reason == "gap of 467 ms (rate 15 Hz)"
    assert not cp.predicting
    assert _setpoint(est, t_ns) is None


def test_refused_sample_is_skipped_and_counted() -> None:
    est = _estimate()
    _warm(est, 20)
    cp = est.filter.predictor
    assert cp is not None
    last = cp.last_t_ns
    cp.update(np.zeros(3), T0_NS)   # back in time
    assert (cp.refused, cp.last_t_ns) == (1, last)


def test_compiled_and_numpy_setpoints_agree() -> None:
    """:meth:`Estimate.setpoint_of_line` compiled (``tcp_setpoint``) and in numpy, on a chain
    with rotations and a turning change."""
    est = chain_estimate(RigidTransform.from_rotvec((0.1, 0.2, 0.0), (10.0, -20.0, 300.0)),
                         RigidTransform.from_rotvec((0.0, 0.3, 0.1), (100.0, 0.0, 200.0)),
                         RigidTransform.from_translation(ENTRY_MM),
                         RigidTransform.from_rotvec((0.0, 0.0, 0.01)))
    x = np.array([1.0, -2.0, 3.0, 0.01, -0.02, 0.005])
    v = np.array([5.0, 1.0, -3.0, 0.02, 0.01, -0.03])
    was = native.use_native(True)
    try:
        assert native.active() is not None, native.native_status()
        D_c, vel_c, w_c = est.setpoint_of_line(x, v, 0.091, 0.15)
        native.use_native(False)
        assert native.active() is None
        D_n, vel_n, w_n = est.setpoint_of_line(x, v, 0.091, 0.15)
    finally:
        native.use_native(was)
    np.testing.assert_allclose(D_c.R, D_n.R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(D_c.t, D_n.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(vel_c, vel_n, rtol=0, atol=1e-7)
    np.testing.assert_allclose(w_c, w_n, rtol=0, atol=1e-9)
    assert float(np.linalg.norm(vel_n)) > 1.0


def test_alpha_beta_is_the_filter_alone() -> None:
    est = chain_estimate(RigidTransform.identity(), RigidTransform.identity(),
                         RigidTransform.from_translation(ENTRY_MM), RigidTransform.identity())
    assert est.filter.predictor is None
    t_ns = _feed(est, 0, np.zeros(3))
    assert _setpoint(est, t_ns) is None
    assert _predictor_fields(est) == {}


def test_registration_resets_the_predictor() -> None:
    est = _estimate()
    _warm(est)
    est.restart_registration()
    cp = est.filter.predictor
    assert cp is not None
    assert (cp.last_t_ns, cp.predicting) == (None, False)


def test_a_learning_predictor_needs_the_camera_rate() -> None:
    cfg = ProcedureConfig.model_validate({"compensation": {"predictor": "ar-ls"}})
    plan = load_plan("configs/plans/sim_plan.json")
    rig = RigGeometry(RigidTransform.identity(), np.zeros((3, 3)), RigidTransform.identity())
    with pytest.raises(ConfigError, match="needs the camera's frame rate"):
        Estimate(plan, rig, cfg)
    est = Estimate(plan, rig, cfg, RATE_HZ)
    assert est.filter.predictor is not None
    assert est.filter.predictor.predictor.rate_hz == RATE_HZ


def test_config_names_every_predictor() -> None:
    field = CompensationConfig.model_fields["predictor"]
    assert set(typing.get_args(field.annotation)) == set(PREDICTOR_NAMES)
    assert CompensationConfig().predictor == "alpha-beta"
