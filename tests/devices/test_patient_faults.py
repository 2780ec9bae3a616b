"""Patient faults played by the simulated world (issue 41): a cough, a shift, a marker lost or
moved — exact displacements on the rigid phantom, the camera's markers, the config's checks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from drivers.sim.camera import SimStereoCamera
from drivers.sim.patient_faults import COUGH_WEIGHT_MIN, bump, cough_weight, ramp
from drivers.sim.world import SimWorld
from hil.clock import ManualClock
from hil.config import build_devices, load_setup
from hil.config.faults import FaultKind, FaultSpec
from hil.config.setup import FramesConfig
from hil.config.simulation import BreathingConfig, SimulationConfig, TremorConfig
from hil.errors import ConfigError

#: a phantom that does not move by itself: every displacement below is the fault's
STILL = SimulationConfig(seed=2, tremor=TremorConfig(amplitude_mm=0.0),
                         breathing=BreathingConfig(amplitude_mm=0.0))


def _world(*faults: FaultSpec) -> tuple[SimWorld, ManualClock]:
    clock = ManualClock()
    return SimWorld(STILL, FramesConfig(), clock, faults), clock


def _image(world: SimWorld, clock: ManualClock, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Markers, entry and target in the image frame at world time ``t_s``."""
    b = world.body_state(world.t0_ns + round(t_s * 1e9))
    inv = world.T_optical_from_image0.inverse()
    return inv.apply(b.markers_mm), inv.apply(b.entry_mm), inv.apply(b.target_mm)


def test_bump_and_ramp_shapes() -> None:
    assert bump(0.9, 1.0, 2.0) == 0.0
    assert bump(1.0, 1.0, 2.0) == 0.0
    assert bump(2.0, 1.0, 2.0) == pytest.approx(1.0)
    assert bump(3.0, 1.0, 2.0) == 0.0
    assert ramp(0.5, 1.0, 2.0) == 0.0
    assert ramp(2.0, 1.0, 2.0) == pytest.approx(0.5)
    assert ramp(3.0, 1.0, 2.0) == 1.0
    assert ramp(30.0, 1.0, 2.0) == 1.0


@given(y=st.floats(-500.0, 500.0, allow_nan=False), entry_y=st.floats(-200.0, 200.0, allow_nan=False))
def test_cough_weight_is_bounded_and_monotonic(y: float, entry_y: float) -> None:
    w = float(cough_weight(np.array([y]), entry_y)[0])
    assert COUGH_WEIGHT_MIN <= w <= 1.0
    assert float(cough_weight(np.array([y + 1.0]), entry_y)[0]) >= w


def test_patient_shift_moves_everything_and_stays() -> None:
    world, clock = _world(FaultSpec(kind=FaultKind.PATIENT_SHIFT, start_s=1.0, duration_s=0.5))
    m0, e0, t0 = _image(world, clock, 0.0)
    off = np.array([5.0, 3.0, 0.0])                    # the kind's default
    for t_s, part in ((0.9, 0.0), (1.25, 0.5), (1.5, 1.0), (20.0, 1.0)):
        m, e, t = _image(world, clock, t_s)
        np.testing.assert_allclose(m - m0, np.tile(part * off, (len(m0), 1)), atol=1e-9)
        np.testing.assert_allclose(e - e0, part * off, atol=1e-9)
        np.testing.assert_allclose(t - t0, part * off, atol=1e-9)


def test_cough_is_a_non_rigid_jolt_that_ends() -> None:
    off = (0.0, 4.0, 6.0)
    world, clock = _world(FaultSpec(kind=FaultKind.COUGH, start_s=2.0, duration_s=0.8, offset_mm=off))
    m0, e0, t0 = _image(world, clock, 0.0)
    m, e, t = _image(world, clock, 2.4)                # the peak
    w = cough_weight(m0[:, 1], float(e0[1]))
    np.testing.assert_allclose(m - m0, w[:, None] * np.array(off), atol=1e-9)
    w_entry = float(cough_weight(np.array([e0[1]]), float(e0[1]))[0])
    np.testing.assert_allclose(e - e0, w_entry * np.array(off), atol=1e-9)
    np.testing.assert_allclose(t - t0, w_entry * np.array(off), atol=1e-9)
    assert np.ptp(w) > 0.05                            # the markers do not move as one body
    assert world.body_rigid_residual_mm(world.t0_ns + round(2.4e9)) > 0.05
    m_end, _, _ = _image(world, clock, 2.8)
    np.testing.assert_allclose(m_end, m0, atol=1e-9)


def test_marker_moved_slides_and_stays() -> None:
    spec = FaultSpec(kind=FaultKind.MARKER_MOVED, start_s=1.0, duration_s=1.0, markers=(1, 3, 99))
    world, clock = _world(spec)
    m0, _, _ = _image(world, clock, 0.0)
    moved = np.zeros_like(m0)
    moved[[1, 3]] = [12.0, 0.0, 0.0]                   # the default; index 99 does not exist: ignored
    for t_s, part in ((0.99, 0.0), (1.5, 0.5), (2.0, 1.0), (30.0, 1.0)):
        np.testing.assert_allclose(_image(world, clock, t_s)[0] - m0, part * moved, atol=1e-9)


def test_marker_lost_hides_it_from_the_camera_only() -> None:
    """Through the setup: the world built for the sim camera plays the setup's patient fault."""
    spec = FaultSpec(kind=FaultKind.MARKER_LOST, start_s=1.0, duration_s=1.0, markers=(2,))
    setup = load_setup("configs/sim.toml")
    clock = ManualClock()
    devices = build_devices(setup.model_copy(update={"faults": (spec,)}), clock)
    cam = devices.camera
    assert isinstance(cam, SimStereoCamera)                # a patient fault wraps no device
    world = cam.world
    t0 = world.t0_ns
    assert world.lost_markers(t0 + round(0.5e9)) == frozenset()
    assert world.lost_markers(t0 + round(1.5e9)) == frozenset({2})
    assert world.lost_markers(t0 + round(2.0e9)) == frozenset()
    n = len(world.phantom.markers_mm)
    ids_before = [m.marker_id for m in cam.markers_at(t0 + round(0.5e9)) if m.marker_id < n]
    ids_during = [m.marker_id for m in cam.markers_at(t0 + round(1.5e9)) if m.marker_id < n]
    assert ids_before == list(range(n))
    assert ids_during == [i for i in range(n) if i != 2]
    # the truth still has it (it is there; the camera does not see it)
    assert len(world.patient_markers_optical(t0 + round(1.5e9))[0]) == n


@pytest.mark.parametrize(("fault", "message"), [
    ({"kind": "cough", "start_s": 1, "duration_s": 1, "markers": [1]}, "do not apply to a cough"),
    ({"kind": "marker_lost", "start_s": 1, "duration_s": 1, "offset_mm": [1, 2, 3]}, "do not apply"),
    ({"kind": "marker_moved", "start_s": 1, "duration_s": 1, "markers": [-1]}, "indices are >= 0"),
    ({"kind": "marker_moved", "start_s": 1, "duration_s": 1, "markers": []}, "at least 1"),
    ({"kind": "patient_shift", "start_s": 1, "duration_s": 1, "offset_mm": [1, 2, 500]}, "within 100 mm"),
    ({"kind": "cough", "start_s": 1, "duration_s": 1, "offset_mm": [1, float("nan"), 3]}, "finite"),
])
def test_bad_patient_fault_is_refused_with_the_reason(fault: dict[str, object], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        FaultSpec.model_validate(fault)


def test_patient_fault_needs_a_simulated_world() -> None:
    """A setup with no simulated device cannot play a cough: refused before any device opens."""
    setup = load_setup("configs/ur3_v4l2.toml")
    spec = FaultSpec(kind=FaultKind.COUGH, start_s=1.0, duration_s=0.5)
    bad = setup.model_copy(update={"faults": (spec,)})
    with pytest.raises(ConfigError, match="cough happen to the patient, which only the simulated world"):
        build_devices(bad, ManualClock())
