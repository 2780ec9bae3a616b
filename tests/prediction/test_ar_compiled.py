"""The loop's ``ar-ls`` predictor compiled (hil/geometry/_native.c ``ar_feed`` / ``ar_forecast``)
against its numpy reference (hil/prediction/ar.py): the same forecasts to rounding on breathing,
a drift, a breath hold (an ill-conditioned window), after a reset, at every fractional step; and
the guard around each the same. The extension must be built here (tools/test builds it)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.geometry import native
from hil.prediction import SafetyLimits, make_predictor
from hil.prediction.ar import ArModel


@pytest.fixture
def both() -> tuple[ArModel, ArModel]:
    assert native.active() is not None, native.native_status()
    prev = native.use_native(False)
    try:
        ref = ArModel(order=6, window=60)
    finally:
        native.use_native(prev)
    fast = ArModel(order=6, window=60)
    assert not ref.compiled
    assert fast.compiled
    return ref, fast


def _breathing(n: int, seed: int = 0) -> np.ndarray:
    t = np.arange(n) / 15.0
    rng = np.random.default_rng(seed)
    x = np.outer(10.0 * np.cos(np.pi * t / 4.0) ** 4, [0.2, 0.5, 1.0]) + 0.3 * t[:, None] / t[-1]
    x[n // 2: n // 2 + 60] = x[n // 2]          # a breath hold: the window goes flat
    return x + rng.normal(0.0, 0.02, x.shape)


def test_compiled_and_numpy_forecasts_agree_to_rounding(both: tuple[ArModel, ArModel]) -> None:
    ref, fast = both
    x = _breathing(600)
    checked = 0
    for i, xi in enumerate(x):
        ref.feed(xi, 1.0)
        fast.feed(xi, 1.0)
        assert fast.ready == ref.ready
        if ref.ready:
            for steps in (0.0, 0.4, 1.0, 1.5, 2.25, 3.0):
                np.testing.assert_allclose(fast.forecast(steps), ref.forecast(steps), rtol=0, atol=1e-9)
            checked += 1
        if i == 400:
            ref.reset()
            fast.reset()
            assert not fast.ready
    assert checked > 400


@settings(max_examples=25, deadline=None)
@given(st.integers(min_value=1, max_value=8), st.integers(min_value=2, max_value=40),
       st.integers(min_value=0, max_value=2**31 - 1))
def test_any_order_and_window_agree(order: int, extra: int, seed: int) -> None:
    prev = native.use_native(False)
    try:
        ref = ArModel(order=order, window=order + extra)
    finally:
        native.use_native(prev)
    fast = ArModel(order=order, window=order + extra)
    x = np.random.default_rng(seed).normal(0.0, 1.0, (3 * (order + extra) + 5, 3)).cumsum(axis=0)
    for xi in x:
        ref.feed(xi, 1.0)
        fast.feed(xi, 1.0)
        if ref.ready:
            np.testing.assert_allclose(fast.forecast(2.5), ref.forecast(2.5), rtol=1e-9, atol=1e-9)
    assert fast.ready == ref.ready


def test_the_guarded_predictor_is_the_same_with_either() -> None:
    """The loop's predictor (guard, fallbacks at an innovation) on a cough: same outputs."""
    x = _breathing(450, seed=3)
    x[300] += np.array([0.0, 0.0, 6.0])          # a cough: the innovation guard falls back
    outs = {}
    for compiled in (False, True):
        prev = native.use_native(compiled)
        try:
            p = make_predictor("ar-ls", 15.0, SafetyLimits(max_horizon_s=0.15))
        finally:
            native.use_native(prev)
        ys = []
        for i, xi in enumerate(x):
            p.update(i / 15.0, xi)
            ys.append(np.concatenate([p.predict(0.035), p.predict(0.1)]))
        outs[compiled] = (np.array(ys), p.fallbacks)
    np.testing.assert_allclose(outs[True][0], outs[False][0], rtol=0, atol=1e-9)
    assert outs[True][1] == outs[False][1] >= 1


def test_bad_state_is_a_typed_error() -> None:
    k = native.active()
    assert k is not None
    with pytest.raises(ValueError, match="shapes do not match"):
        k.ar_feed(np.zeros(3), np.zeros((10, 3)), np.zeros((3, 36)), np.zeros((3, 6)), np.zeros((3, 6)),
                  np.zeros(3), np.zeros(4), 6, 60, 1e-4)
    with pytest.raises(TypeError, match="float64"):
        k.ar_forecast(1.0, np.zeros((67, 3), dtype=np.float32), np.zeros((3, 6)), np.zeros(3),
                      np.zeros(4), 6, np.zeros(3))
