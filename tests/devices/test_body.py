"""The deformable patient (issue 40): skin field, target motion, normals, holds, residual."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from drivers.sim.body import NORMAL_STEP_MM, SkinField, SmoothField
from drivers.sim.world import SimWorld
from hil.clock import ManualClock
from hil.config.body import BodyConfig, SkinFieldConfig, TargetMotionConfig
from hil.config.setup import FramesConfig
from hil.config.simulation import BreathHoldConfig, BreathingConfig, SimulationConfig, TremorConfig
from hil.geometry.thin_plate import thin_plate_weights

STILL = TremorConfig(amplitude_mm=0.0)


def _world(seed: int = 3, **body: object) -> tuple[SimWorld, ManualClock]:
    sim = SimulationConfig(seed=seed, tremor=STILL, body=BodyConfig(model="deformable", **body))
    clock = ManualClock()
    return SimWorld(sim, FramesConfig(), clock), clock


def _at(world: SimWorld, clock: ManualClock, t_s: float) -> int:
    return clock.now_ns() + round(t_s * 1e9)


def _in_image(world: SimWorld, pts: np.ndarray) -> np.ndarray:
    return world.T_optical_from_image0.inverse().apply(pts)


def test_rigid_is_the_default_and_has_no_body() -> None:
    clock = ManualClock()
    world = SimWorld(SimulationConfig(), FramesConfig(), clock)
    assert world.body is None
    t = _at(world, clock, 1.3)
    T = world.T_optical_from_image(t)
    markers, normals = world.patient_markers_optical(t)
    assert np.array_equal(markers, T.apply(world.phantom.markers_mm))
    assert np.array_equal(normals, T.apply_vector(world.phantom.normals))
    assert np.array_equal(world.target_optical(t), T.apply(world.phantom.target_mm))
    assert world.body_rigid_residual_mm(t) == 0.0


def test_at_rest_the_body_is_the_ct() -> None:
    world, clock = _world()
    b = world.body_state(clock.now_ns())
    T = world.T_optical_from_image0
    assert np.allclose(b.markers_mm, T.apply(world.phantom.markers_mm), atol=1e-12)
    assert np.allclose(b.entry_mm, T.apply(world.phantom.entry_mm), atol=1e-12)
    assert np.allclose(b.target_mm, T.apply(world.phantom.target_mm), atol=1e-12)
    # the finite-difference normal of the cylinder is its normal to O(step / radius)
    assert np.allclose(b.normals, T.apply_vector(world.phantom.normals), atol=2 * NORMAL_STEP_MM / 180.0)
    assert np.allclose(np.linalg.norm(b.normals, axis=1), 1.0)


def test_same_seed_same_body_whatever_the_order() -> None:
    a, ca = _world(seed=11)
    b, cb = _world(seed=11)
    times = [0.3, 2.1, 5.7, 1.0]
    first = [a.body_state(_at(a, ca, t)).markers_mm for t in times]
    second = [b.body_state(_at(b, cb, t)).markers_mm for t in reversed(times)][::-1]
    for x, y in zip(first, second, strict=True):
        assert np.array_equal(x, y)


def _one_breath(world: SimWorld, clock: ManualClock) -> tuple[np.ndarray, np.ndarray]:
    ts = np.arange(0.0, 8.0, 0.05)
    states = [world.body_state(_at(world, clock, t)) for t in ts]
    markers = np.array([_in_image(world, s.markers_mm) for s in states])
    target = np.array([_in_image(world, s.target_mm[None, :])[0] for s in states])
    return markers, target


def test_markers_move_by_different_amounts_in_different_directions() -> None:
    world, clock = _world()
    markers, _ = _one_breath(world, clock)
    ptp, dirs = [], []
    for i in range(markers.shape[1]):
        d = markers[:, i] - markers[:, i].mean(axis=0)
        u = np.linalg.svd(d, full_matrices=False)[2][0]
        u = u if u[2] > 0 else -u
        proj = d @ u
        ptp.append(proj.max() - proj.min())
        dirs.append(u)
    assert max(ptp) / min(ptp) > 1.3
    spread = max(math.degrees(math.acos(min(1.0, float(a @ b)))) for a in dirs for b in dirs)
    assert spread > 10.0
    residual = max(world.body_rigid_residual_mm(_at(world, clock, t)) for t in np.arange(0, 4, 0.1))
    assert residual > 0.3


def test_thoracic_and_abdominal_regions_have_their_amplitude() -> None:
    cfg = SkinFieldConfig(thoracic_amplitude_mm=3.0, abdominal_amplitude_mm=12.0, amplitude_variation=0.0,
                          direction_variation_deg=0.0, boundary_y_mm=0.0, transition_mm=10.0)
    basis = SkinField(cfg, seed=1).basis(np.array([[0.0, 200.0], [0.0, -200.0]]))
    assert np.linalg.norm(basis.thoracic_mm[0]) == pytest.approx(3.0, abs=1e-9)
    assert np.linalg.norm(basis.abdominal_mm[1]) == pytest.approx(12.0, abs=1e-9)
    assert np.linalg.norm(basis.abdominal_mm[0]) < 1e-9
    assert np.linalg.norm(basis.thoracic_mm[1]) < 1e-9


def test_target_moves_on_its_own_with_hysteresis() -> None:
    world, clock = _world(target=TargetMotionConfig(amplitude_mm=10.0, hysteresis_mm=3.0, lag_s=0.2,
                                                    hold_reproducibility_mm=0.0))
    _, target = _one_breath(world, clock)
    rest = world.phantom.target_mm
    d = target - rest
    u = np.array([0.0, -1.0, 0.25]) / math.hypot(1.0, 0.25)
    along = d @ u
    assert 8.0 < along.max() < 12.0
    # the target is not a rigid copy of the skin: its offset from the entry changes
    entry = np.array([_in_image(world, world.body_state(_at(world, clock, t)).entry_mm[None, :])[0]
                      for t in np.arange(0.0, 8.0, 0.05)])
    rel = target - entry
    assert np.ptp(np.linalg.norm(rel, axis=1)) > 3.0
    # inhale and exhale pass the same superior-inferior level at different anterior offsets
    v = np.array([0.0, 0.0, 1.0]) - (np.array([0.0, 0.0, 1.0]) @ u) * u
    v /= np.linalg.norm(v)
    across = d @ v
    first = slice(0, int(4.0 / 0.05))
    k_peak = int(np.argmax(along[first]))
    level = 0.5 * along[k_peak]
    up = int(np.argmin(np.abs(along[:k_peak] - level)))
    down = k_peak + int(np.argmin(np.abs(along[k_peak:first.stop] - level)))
    assert abs(across[up] - across[down]) > 0.5


def test_each_breath_hold_leaves_the_target_somewhere_else() -> None:
    holds = (BreathHoldConfig(start_s=1.0, duration_s=4.0), BreathHoldConfig(start_s=9.0, duration_s=4.0))
    sim = SimulationConfig(seed=5, tremor=STILL, breath_holds=holds,
                           breathing=BreathingConfig(irregularity=0.0),
                           body=BodyConfig(model="deformable",
                                           target=TargetMotionConfig(hold_reproducibility_mm=2.0)))
    clock = ManualClock()
    world = SimWorld(sim, FramesConfig(), clock)
    a = world.body_state(_at(world, clock, 4.0))
    b = world.body_state(_at(world, clock, 12.0))
    # the skin is back at end-exhale both times; the target is not at the same place
    assert np.allclose(a.markers_mm, b.markers_mm, atol=1e-9)
    gap = float(np.linalg.norm(a.target_mm - b.target_mm))
    assert gap > 0.05
    expected = world.body.target_motion.hold_offset_mm(0) - world.body.target_motion.hold_offset_mm(1)
    assert np.allclose(_in_image(world, a.target_mm[None, :]) - _in_image(world, b.target_mm[None, :]),
                       expected, atol=1e-9)


def test_a_hold_without_reproducibility_error_is_exact() -> None:
    holds = (BreathHoldConfig(start_s=1.0, duration_s=4.0),)
    sim = SimulationConfig(seed=5, tremor=STILL, breath_holds=holds,
                           body=BodyConfig(model="deformable",
                                           target=TargetMotionConfig(hold_reproducibility_mm=0.0)))
    clock = ManualClock()
    world = SimWorld(sim, FramesConfig(), clock)
    b = world.body_state(_at(world, clock, 4.0))
    assert np.allclose(_in_image(world, b.target_mm[None, :])[0], world.phantom.target_mm, atol=1e-9)


def test_body_config_is_checked() -> None:
    with pytest.raises(ValidationError, match="needs model"):
        BodyConfig(trace={"path": "x.csv"})
    with pytest.raises(ValidationError, match="must not be zero"):
        SkinFieldConfig(thoracic_direction=(0.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match="parallel"):
        TargetMotionConfig(direction=(0.0, 1.0, 0.0), hysteresis_direction=(0.0, -2.0, 0.0))
    with pytest.raises(ValidationError, match="point name"):
        BodyConfig(model="deformable", trace={"points": {"a b": (0.0, 0.0)}})


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31), st.floats(-300, 300), st.floats(-300, 300))
def test_smooth_field_is_bounded_and_smooth(seed: int, x: float, y: float) -> None:
    f = SmoothField(seed, "a", 140.0)
    p = np.array([[x, y]])
    v = float(f(p)[0])
    assert -1.0 <= v <= 1.0
    # Lipschitz: the wave number bounds the slope
    k = 2.0 * math.pi / 140.0
    assert abs(float(f(p + 0.1)[0]) - v) <= k * 0.1 * math.sqrt(2.0) + 1e-12


places = st.lists(st.tuples(st.floats(-150, 150), st.floats(-150, 150)), min_size=3, max_size=8)


@settings(max_examples=60, deadline=None)
@given(places, st.floats(-2, 2), st.floats(-2, 2), st.floats(-50, 50))
def test_thin_plate_spline_is_exact_at_places_and_on_affine_fields(
        pts: list[tuple[float, float]], a: float, b: float, c: float) -> None:
    xy = np.array(pts)
    sv = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    gaps = np.linalg.norm(xy[:, None] - xy[None], axis=2) + np.eye(len(xy)) * 1e9
    assume(sv[1] >= 5.0 and gaps.min() >= 5.0)   # well-conditioned layouts (refusals: below)
    W = thin_plate_weights(xy, xy)
    assert np.allclose(W, np.eye(len(xy)), atol=1e-6)
    query = np.array([[0.0, 0.0], [70.0, -20.0], [-120.0, 140.0]])
    values = a * xy[:, 0] + b * xy[:, 1] + c
    expected = a * query[:, 0] + b * query[:, 1] + c
    assert np.allclose(thin_plate_weights(xy, query) @ values, expected, atol=1e-6 * (1 + abs(c)))


def test_thin_plate_refuses_what_it_cannot_fit() -> None:
    with pytest.raises(ValueError, match="at least 3"):
        thin_plate_weights(np.array([[0.0, 0.0], [1.0, 0.0]]), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="collinear"):
        thin_plate_weights(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="same place"):
        thin_plate_weights(np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 0.0]]), np.zeros((1, 2)))
