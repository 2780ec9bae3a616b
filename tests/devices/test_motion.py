"""Scripted motion: pure functions of time and seed; reproducible; the breathing model's shape."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.sim.motion import BreathingScript, PatientMotion, drift_mm, hold_weight, shift_transform
from drivers.sim.world import SimWorld, phantom_from_config
from hil.clock import ManualClock
from hil.config import (
    BreathHoldConfig,
    BreathingConfig,
    DriftConfig,
    FramesConfig,
    PatientConfig,
    ShiftConfig,
    SimulationConfig,
    TremorConfig,
)

TIMES = np.linspace(0.0, 30.0, 301)


def _sim(seed: int, **kw: object) -> SimulationConfig:
    return SimulationConfig(seed=seed, drift=DriftConfig(velocity_mm_s=(0.05, 0.0, 0.0), max_mm=1.0),
                            shifts=(ShiftConfig(at_s=12.0, translation_mm=(2.0, 0.0, 0.0),
                                                rotvec_rad=(0.0, 0.0, 0.02)),), **kw)  # type: ignore[arg-type]


def _trajectory(motion: PatientMotion, times: np.ndarray) -> np.ndarray:
    return np.array([motion.sample(float(t)).T_image0_from_image.as_matrix() for t in times])


def test_same_seed_reproduces_exactly_in_any_query_order() -> None:
    a = _trajectory(PatientMotion(_sim(3)), TIMES)
    b = _trajectory(PatientMotion(_sim(3)), TIMES[::-1])[::-1]
    assert np.array_equal(a, b)


def test_different_seeds_differ() -> None:
    a = _trajectory(PatientMotion(_sim(3)), TIMES)
    b = _trajectory(PatientMotion(_sim(4)), TIMES)
    assert not np.allclose(a, b)


def test_world_reproduces_marker_positions_from_the_seed() -> None:
    def run() -> list[np.ndarray]:
        clock = ManualClock(5)
        world = SimWorld(_sim(9), FramesConfig(), clock)
        out = []
        for _ in range(50):
            clock.advance(0.137)
            out.append(world.patient_markers_optical(clock.now_ns())[0])
        return out

    assert all(np.array_equal(x, y) for x, y in zip(run(), run(), strict=True))


def test_lujan_breathing_shape_regular() -> None:
    """No irregularity: peak A at mid active phase, 0 through the end-exhale dwell, period T."""
    cfg = BreathingConfig(amplitude_mm=8.0, period_s=4.0, shape_n=2, end_exhale_dwell_s=1.0,
                          irregularity=0.0)
    b = BreathingScript(cfg, seed=0)
    active = 3.0
    assert math.isclose(b.displacement_mm(active / 2), 8.0)
    assert b.displacement_mm(3.5) == 0.0           # dwell
    assert b.displacement_mm(0.0) == 0.0
    s = 0.25
    assert math.isclose(b.displacement_mm(s * active), 8.0 * math.cos(math.pi * (s - 0.5)) ** 4)
    for t in (0.3, 1.1, 2.9):
        assert math.isclose(b.displacement_mm(t), b.displacement_mm(t + 4.0 * 7))


@given(st.floats(0.0, 200.0), st.integers(0, 2**31), st.floats(0.0, 0.5))
def test_breathing_stays_within_the_irregular_amplitude(t: float, seed: int, irr: float) -> None:
    cfg = BreathingConfig(amplitude_mm=5.0, period_s=4.0, end_exhale_dwell_s=0.5, irregularity=irr)
    d = BreathingScript(cfg, seed).displacement_mm(t)
    assert 0.0 <= d <= 5.0 * (1 + irr) + 1e-12


def test_irregular_cycles_vary_in_period_and_amplitude() -> None:
    cfg = BreathingConfig(irregularity=0.3)
    b = BreathingScript(cfg, seed=1)
    cycles = [b._cycle(k) for k in range(10)]
    periods = {round(c[1], 6) for c in cycles}
    amps = {round(c[2], 6) for c in cycles}
    assert len(periods) == 10
    assert len(amps) == 10
    assert all(2.8 - 1e-9 <= p <= 5.2 + 1e-9 for p in periods)


def test_breath_hold_replaces_breathing_with_the_level() -> None:
    sim = SimulationConfig(breathing=BreathingConfig(irregularity=0.0), tremor=TremorConfig(amplitude_mm=0.0),
                           breath_holds=(BreathHoldConfig(start_s=10.0, duration_s=5.0, level=0.0),),
                           hold_ramp_s=0.5)
    m = PatientMotion(sim)
    for t in np.linspace(10.5, 15.0, 20):
        assert m.sample(float(t)).breathing_mm == 0.0
        assert m.sample(float(t)).T_image0_from_image.is_close(m.sample(10.6).T_image0_from_image)
    assert m.sample(9.0).hold_weight == 0.0
    assert m.sample(12.0).hold_weight == 1.0
    assert 0.0 < m.sample(10.25).hold_weight < 1.0


def test_requested_breath_hold_starts_after_the_reaction_time() -> None:
    clock = ManualClock()
    world = SimWorld(SimulationConfig(hold_reaction_s=1.0, tremor=TremorConfig(amplitude_mm=0.0)),
                     FramesConfig(), clock)
    clock.advance(3.0)
    start = world.request_breath_hold(4.0)
    assert start == 4.0
    a = world.patient_markers_optical(clock.now_ns() + 2_000_000_000)[0]
    b = world.patient_markers_optical(clock.now_ns() + 4_000_000_000)[0]
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_hold_weight_ramps() -> None:
    h = BreathHoldConfig(start_s=1.0, duration_s=2.0)
    assert [hold_weight(t, h, 0.2) for t in (0.9, 1.0, 1.2, 2.0, 3.0, 3.2)] == [0.0, 0.0, 1.0, 1.0, 1.0, 0.0]


def test_drift_is_clamped() -> None:
    cfg = DriftConfig(velocity_mm_s=(3.0, 4.0, 0.0), max_mm=10.0)
    np.testing.assert_allclose(drift_mm(1.0, cfg), [3.0, 4.0, 0.0])
    np.testing.assert_allclose(drift_mm(100.0, cfg), [6.0, 8.0, 0.0])


def test_shift_is_a_ramped_step() -> None:
    sh = (ShiftConfig(at_s=5.0, translation_mm=(0.0, 3.0, 0.0), ramp_s=0.1),)
    assert shift_transform(4.99, sh).is_close(shift_transform(0.0, sh))
    np.testing.assert_allclose(shift_transform(5.2, sh).t, [0.0, 3.0, 0.0])


@given(st.integers(3, 12), st.floats(0.0, 1.0))
def test_phantom_markers_lie_on_the_skin_apart(n: int, f: float) -> None:
    spread = max(1.4 * 7.0 * math.sqrt(n), 20.01) + f * 100.0
    cfg = PatientConfig(marker_count=n, marker_spread_mm=spread)
    ph = phantom_from_config(cfg)
    assert ph.markers_mm.shape == (n, 3)
    R = cfg.torso_radius_mm
    radial = np.hypot(ph.markers_mm[:, 0], ph.markers_mm[:, 2] + R)
    np.testing.assert_allclose(radial, R)
    np.testing.assert_allclose(np.linalg.norm(ph.normals, axis=1), 1.0)
    d = np.linalg.norm(ph.markers_mm[:, None] - ph.markers_mm[None], axis=2) + np.eye(n) * 1e9
    assert d.min() > 2 * cfg.marker_outer_diameter_mm
    assert ph.target_mm[2] < ph.entry_mm[2] - 50.0


def test_crowded_markers_are_refused() -> None:
    with pytest.raises(ValueError, match="too small for 11 markers"):
        PatientConfig(marker_count=11, marker_spread_mm=30.0)
