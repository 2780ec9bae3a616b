"""Property: for any finite input the output is finite and departs from the last sample by at
most the guard's bound (hil/prediction/base.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.prediction import PREDICTOR_NAMES, PredictionError, make_predictor

RATE_HZ = 30.0

samples = st.lists(
    st.tuples(st.floats(0.5, 1.6), st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3)),
    min_size=1, max_size=150,
)


@settings(max_examples=40, deadline=None)
@given(name=st.sampled_from(PREDICTOR_NAMES), seq=samples, h_s=st.floats(0.0, 1.0))
def test_output_is_finite_and_bounded(name: str, seq: list[tuple[float, list[float]]], h_s: float) -> None:
    p = make_predictor(name, RATE_HZ)
    t = 0.0
    for steps, x in seq:
        t += steps / RATE_HZ
        xa = np.array(x)
        p.update(t, xa)
        out = p.predict(h_s)
        assert out.shape == (3,)
        assert np.isfinite(out).all()
        h = min(h_s, p.limits.max_horizon_s)
        cap = min(p.limits.max_departure_mm, p.limits.max_speed_mm_s * h)
        assert np.linalg.norm(out - xa) <= cap * (1 + 1e-12) + 1e-9


@given(x=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3, max_size=3))
def test_non_finite_positions_are_refused(x: list[float]) -> None:
    p = make_predictor("ar-ls", RATE_HZ)
    xa = np.array(x)
    if np.isfinite(xa).all():
        p.update(0.0, xa)
        return
    with pytest.raises(PredictionError, match="not finite"):
        p.update(0.0, xa)
