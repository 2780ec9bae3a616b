"""The predictors on synthetic signals: exact answers where they exist, stated bounds otherwise,
and the guard's rules (hil/prediction/base.py): bounded output, counted fallbacks, refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.prediction import PREDICTOR_NAMES, GuardedPredictor, PredictionError, SafetyLimits, make_predictor
from tests.prediction.signals import sinusoid

RATE_HZ = 15.0
DT_S = 1.0 / RATE_HZ
H_S = 0.06
LEARNING = ("wlms", "ar-ls", "kalman-osc")
ALL_LEARNING = (*LEARNING, "fast-lane")


def feed(p: GuardedPredictor, t: np.ndarray, x: np.ndarray) -> None:
    for ti, xi in zip(t, x, strict=True):
        p.update(float(ti), xi)


def cap_mm(p: GuardedPredictor, h_s: float) -> float:
    return min(p.limits.max_departure_mm, p.limits.max_speed_mm_s * min(h_s, p.limits.max_horizon_s))


@pytest.mark.parametrize("name", PREDICTOR_NAMES)
def test_constant_signal_is_predicted_exactly(name: str) -> None:
    p = make_predictor(name, RATE_HZ)
    c = np.array([12.5, -3.0, 40.0])
    feed(p, np.arange(300) * DT_S, np.tile(c, (300, 1)))
    for h in (0.0, 0.033, 0.06, 0.15):
        np.testing.assert_allclose(p.predict(h), c, rtol=0, atol=1e-9)
    assert p.fallbacks == 0
    assert p.last_fallback_reason is None


def _sinusoid_rms(name: str) -> float:
    p = make_predictor(name, RATE_HZ)
    t = np.arange(0.0, 90.0, DT_S)
    x = sinusoid(t)
    errs = []
    for i, ti in enumerate(t):
        p.update(float(ti), x[i])
        if ti >= 60.0:
            errs.append(float(np.linalg.norm(p.predict(H_S) - sinusoid(ti + H_S))))
    assert p.fallbacks == 0
    return math.sqrt(float(np.mean(np.square(errs))))


def test_sinusoid_learning_predictors_converge() -> None:
    """A pure 4-s sinusoid (10/3/1 mm) at 15 Hz, 60 ms ahead, errors over 60-90 s: each learning
    predictor below 0.02 mm RMS and below a fifth of the alpha-beta filter's (~0.10 mm); no
    prediction is ~0.69 mm."""
    none = _sinusoid_rms("none")
    ab = _sinusoid_rms("alpha-beta")
    assert 0.6 < none < 0.8
    assert 0.05 < ab < 0.15
    for name in ALL_LEARNING:
        rms = _sinusoid_rms(name)
        assert rms < 0.02, name
        assert rms < 0.2 * ab, name


def test_alpha_beta_agrees_with_compensate_filter() -> None:
    """Same gains, same samples: the predictor answers what MotionFilter.estimate does."""
    from hil.controller.compensation import MotionFilter
    from hil.geometry.transform import RigidTransform

    p = make_predictor("alpha-beta", RATE_HZ, SafetyLimits(max_departure_mm=1e9, max_speed_mm_s=1e9,
                                                           innovation_bound_mm=1e9), alpha=0.9, beta=0.7)
    f = MotionFilter(0.9, 0.7)
    rng = np.random.default_rng(3)
    t0_ns = 10**9
    for k in range(200):
        t_ns = t0_ns + round(k * DT_S * 1e9)
        x = sinusoid(k * DT_S) + rng.normal(0, 0.05, 3)
        p.update(t_ns * 1e-9, x)
        f.update(RigidTransform(np.eye(3), x), t_ns)
        for h in (0.033, 0.06, 0.1, 0.15):
            want = f.estimate(t_ns + round(h * 1e9), max_horizon_s=0.2).t
            np.testing.assert_allclose(p.predict(h), want, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", PREDICTOR_NAMES[1:])
def test_patient_shift_is_bounded_and_counted(name: str) -> None:
    """A 10-mm step in the middle of the breathing: one counted innovation fallback, the output
    never departs further than the bound from the last sample, and the predictor recovers."""
    p = make_predictor(name, RATE_HZ)
    t = np.arange(0.0, 60.0, DT_S)
    x = sinusoid(t) + np.where(t >= 30.0, 10.0, 0.0)[:, None] * np.array([1.0, 0.0, 0.0])
    for i, ti in enumerate(t):
        p.update(float(ti), x[i])
        assert np.linalg.norm(p.predict(0.15) - x[i]) <= cap_mm(p, 0.15) + 1e-9
        if abs(ti - 30.0) < 1e-9:
            assert p.fallbacks == 1
            assert p.last_fallback_reason is not None
            assert p.last_fallback_reason.startswith("innovation")
            np.testing.assert_array_equal(p.predict(H_S), x[i])
    assert p.fallbacks == 1
    assert p.predicting


@pytest.mark.parametrize("name", PREDICTOR_NAMES[1:])
def test_cough_spike_is_bounded_and_counted(name: str) -> None:
    """One 8-mm spike: a counted fallback; during the hold the answer is the last sample."""
    p = make_predictor(name, RATE_HZ)
    t = np.arange(0.0, 40.0, DT_S)
    x = sinusoid(t)
    spike = round(20.0 * RATE_HZ)
    x[spike] += np.array([0.0, 8.0, 0.0])
    for i, ti in enumerate(t):
        p.update(float(ti), x[i])
        assert np.linalg.norm(p.predict(0.1) - x[i]) <= cap_mm(p, 0.1) + 1e-9
        if i in (spike + 1, spike + 5):
            np.testing.assert_array_equal(p.predict(H_S), x[i])
    assert p.fallbacks >= 1
    assert p.last_fallback_reason is not None
    assert p.last_fallback_reason.startswith("innovation")


def test_none_never_falls_back_on_a_step() -> None:
    p = make_predictor("none", RATE_HZ)
    feed(p, np.arange(10) * DT_S, np.array([[0.0, 0, 0]] * 5 + [[50.0, 0, 0]] * 5))
    assert p.fallbacks == 0
    np.testing.assert_array_equal(p.predict(0.1), [50.0, 0, 0])


@pytest.mark.parametrize("name", PREDICTOR_NAMES)
def test_nan_sample_is_refused_and_state_kept(name: str) -> None:
    p = make_predictor(name, RATE_HZ)
    t = np.arange(0.0, 10.0, DT_S)
    feed(p, t, sinusoid(t))
    before = p.predict(H_S)
    with pytest.raises(PredictionError, match="not finite"):
        p.update(10.0, np.array([1.0, math.nan, 0.0]))
    with pytest.raises(PredictionError, match="not finite"):
        p.update(math.nan, np.zeros(3))
    np.testing.assert_array_equal(p.predict(H_S), before)


def test_refusals() -> None:
    p = make_predictor("wlms", RATE_HZ)
    with pytest.raises(PredictionError, match="no sample yet"):
        p.predict(0.06)
    p.update(1.0, np.zeros(3))
    with pytest.raises(PredictionError, match="increasing time"):
        p.update(1.0, np.zeros(3))
    with pytest.raises(PredictionError, match="3 values"):
        p.update(2.0, np.zeros(2))
    with pytest.raises(PredictionError, match="horizon"):
        p.predict(-0.01)
    with pytest.raises(PredictionError, match="unknown predictor 'lstm'"):
        make_predictor("lstm", RATE_HZ)
    with pytest.raises(PredictionError, match="rate"):
        make_predictor("ar-ls", 0.0)


@pytest.mark.parametrize("name", LEARNING)
def test_too_short_for_the_window_answers_the_last_sample(name: str) -> None:
    """Until warm (a trace shorter than the window) the prediction is the last sample."""
    p = make_predictor(name, RATE_HZ)
    t = np.arange(8) * DT_S
    x = np.outer(t, [20.0, 0.0, 0.0])  # a 20 mm/s ramp: any extrapolation would move
    feed(p, t, x)
    assert not p.predicting
    np.testing.assert_array_equal(p.predict(0.1), x[-1])
    assert p.fallbacks == 0


@pytest.mark.parametrize("name", PREDICTOR_NAMES[1:])
def test_gap_resets_and_is_counted(name: str) -> None:
    p = make_predictor(name, RATE_HZ)
    t = np.arange(0.0, 20.0, DT_S)
    feed(p, t, sinusoid(t))
    assert p.predicting
    p.update(21.0, sinusoid(21.0))
    assert p.fallbacks == 1
    assert p.last_fallback_reason is not None
    assert p.last_fallback_reason.startswith("gap of 1")
    if name != "alpha-beta":  # alpha-beta is warm after one sample; its velocity restarts at 0
        np.testing.assert_array_equal(p.predict(H_S), sinusoid(21.0))


def test_wrong_rate_resets_and_is_counted() -> None:
    p = make_predictor("ar-ls", RATE_HZ)
    t = np.arange(0.0, 2.0, 1.0 / 60.0)  # a 60 Hz camera fed to a 15 Hz predictor
    feed(p, t, sinusoid(t))
    assert p.fallbacks == len(t) - 1
    assert p.last_fallback_reason is not None
    assert p.last_fallback_reason.startswith("rate")
    np.testing.assert_array_equal(p.predict(H_S), sinusoid(t[-1]))


def test_horizon_is_clamped_to_the_limit() -> None:
    p = make_predictor("alpha-beta", RATE_HZ, SafetyLimits(max_horizon_s=0.1))
    feed(p, np.arange(5) * DT_S, np.outer(np.arange(5) * DT_S, [10.0, 0.0, 0.0]))
    np.testing.assert_array_equal(p.predict(5.0), p.predict(0.1))


def test_fast_lane_answers_with_its_best_lane() -> None:
    """On a pure sinusoid a learning lane beats alpha-beta's one-sample error and answers; before
    the learning lanes are warm, alpha-beta (ready at once) answers."""
    from hil.prediction.fastlane import FastLaneModel

    p = make_predictor("fast-lane", RATE_HZ)
    assert isinstance(p.model, FastLaneModel)
    names = [lane.name for lane in p.model.lanes]
    assert names == ["alpha-beta", "wlms", "ar-ls", "kalman-osc"]
    t = np.arange(0.0, 2.0, DT_S)
    feed(p, t, sinusoid(t))
    assert p.model.best == 0
    t = np.arange(2.0, 60.0, DT_S)
    feed(p, t, sinusoid(t))
    assert names[p.model.best] != "alpha-beta"
