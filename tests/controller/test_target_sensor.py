"""The sensor at the target (hil/controller/target_sensor.py, ``[procedure.tracking] target_sensor``):
its samples' history and the target at a pair's exposure (the simulated sensor:
tests/devices/test_sim_sensors.py), the path pointed at it by the target
model's tracker (the same bound and fade), the fallback to the model with its reason, the session
records, and the setups that cannot carry it."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.interfaces.tracker import TrackerSample
from drivers.sim.planning_ct import four_d_ct_plan
from hil.cli.cmd_run import run_procedure
from hil.config import load_setup
from hil.config.setup import target_sensor_problem
from hil.controller.config import ProcedureConfig
from hil.controller.plan_file import plan_from_dict
from hil.controller.target_model import TargetTracker, fit_target_model
from hil.controller.target_sensor import TargetReading, TargetSensor
from hil.controller.tracker_roles import TrackerRoles
from hil.geometry.transform import RigidTransform, rotvec_to_matrix
from hil.report.session_data import load_session
from hil.session import read_session_log
from tests.controller.test_target_model import ENTRY, FIDUCIALS, TARGET, UNIT, _cycle_plan
from tests.geometry.strategies import rigid_transforms

MS = 1_000_000
T_OT = RigidTransform(rotvec_to_matrix(np.array([math.pi, 0.0, 0.0])), np.array([-190.0, 0.0, 1100.0]))


def _sample(p_tracker: np.ndarray, t_ns: int, seq: int = 0, name: str = "target") -> dict[str, TrackerSample]:
    return {name: TrackerSample(name, RigidTransform.from_translation(p_tracker), 0.1, t_ns, seq)}


def _sensor(max_age_ms: float = 60.0, offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> TargetSensor:
    return TargetSensor("target", np.array(offset), max_age_ms / 1e3, T_OT)


def test_between_two_samples_the_position_is_interpolated_in_the_optical_frame() -> None:
    s = _sensor()
    s.add(_sample(np.array([10.0, 20.0, 30.0]), 100 * MS))
    s.add(_sample(np.array([14.0, 20.0, 26.0]), 125 * MS))
    got = s.position_at(110 * MS)
    assert got.why_not == ""
    assert got.target_optical_mm is not None
    np.testing.assert_allclose(got.target_optical_mm, T_OT.apply(np.array([11.6, 20.0, 28.4])).reshape(3),
                               atol=1e-9)


def test_without_a_pair_of_samples_around_it_the_nearest_within_the_bound_serves() -> None:
    s = _sensor(max_age_ms=60.0)
    s.add(_sample(np.array([1.0, 2.0, 3.0]), 100 * MS))
    s.add(_sample(np.array([9.0, 9.0, 9.0]), 200 * MS))        # 100 ms apart: not interpolated
    near = s.position_at(150 * MS - 1)
    assert near.target_optical_mm is not None
    np.testing.assert_allclose(near.target_optical_mm, T_OT.apply(np.array([1.0, 2.0, 3.0])).reshape(3))
    late = s.position_at(255 * MS)                               # the newest, 55 ms before
    assert late.target_optical_mm is not None
    np.testing.assert_allclose(late.target_optical_mm, T_OT.apply(np.array([9.0, 9.0, 9.0])).reshape(3))
    assert s.position_at(261 * MS) == TargetReading(
        None, "the target sensor's nearest sample is 61 ms from the pair's exposure (bound 60 ms)")
    assert _sensor().position_at(0) == TargetReading(None, "no sample of the target sensor 'target' yet")


def test_missing_repeated_and_other_sensors_samples_are_not_kept() -> None:
    s = _sensor()
    gone = TrackerSample("target", None, None, 100 * MS, 1, missing=True, flags=("out_of_volume",))
    s.add({"target": gone})
    s.add(_sample(np.array([1.0, 0.0, 0.0]), 100 * MS, name="reference"))
    assert s.position_at(100 * MS).target_optical_mm is None
    s.add(_sample(np.array([1.0, 0.0, 0.0]), 100 * MS))
    s.add(_sample(np.array([5.0, 0.0, 0.0]), 100 * MS))          # the same stamp read again
    s.add(_sample(np.array([7.0, 0.0, 0.0]), 90 * MS))           # older than the last kept
    got = s.position_at(100 * MS).target_optical_mm
    assert got is not None
    np.testing.assert_allclose(got, T_OT.apply(np.array([1.0, 0.0, 0.0])).reshape(3))


@settings(max_examples=60, deadline=None)
@given(p0=st.lists(st.floats(-300.0, 300.0), min_size=3, max_size=3),
       v=st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3),
       period_ms=st.integers(5, 60), t_ms=st.floats(0.0, 500.0))
def test_a_sensor_moving_at_constant_velocity_is_found_exactly_between_its_samples(
        p0: list[float], v: list[float], period_ms: int, t_ms: float) -> None:
    s = _sensor(max_age_ms=60.0)
    for k in range(520 // period_ms + 2):
        t = k * period_ms * MS
        s.add(_sample(np.array(p0) + np.array(v) * t * 1e-9, t, k))
    t_ns = round(t_ms * MS)
    got = s.position_at(t_ns).target_optical_mm
    assert got is not None
    want = T_OT.apply(np.array(p0) + np.array(v) * t_ns * 1e-9).reshape(3)
    np.testing.assert_allclose(got, want, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(T=rigid_transforms(max_translation_mm=200.0))
def test_the_target_is_the_sensor_less_its_offset_turned_as_the_patient(T: RigidTransform) -> None:
    offset = np.array([4.0, -3.0, 2.0])
    s = _sensor(offset=(4.0, -3.0, 2.0))
    target = np.array([12.0, -40.0, 900.0])
    p_optical = target + T.R @ offset
    s.add(_sample(T_OT.inverse().apply(p_optical).reshape(3), 100 * MS))
    got = s.target_at(100 * MS, T.R).target_optical_mm
    assert got is not None
    np.testing.assert_allclose(got, target, atol=1e-9)


def _measured(target: np.ndarray) -> TargetReading:
    return TargetReading(np.asarray(target, dtype=np.float64))


def test_the_path_points_at_the_measured_target_from_the_moved_entry() -> None:
    """A target 3 mm off the model's: once the fade is in, the steered path runs from the moved
    entry through the measured target; the entry is the estimator's."""
    plan = _cycle_plan()
    tracker = TargetTracker(fit_target_model(plan, 2.0, 10.0))
    T = RigidTransform.from_translation(np.array([0.5, -0.25, 1.0]))
    live = FIDUCIALS + 6.0 * UNIT
    measured = T.apply(TARGET).reshape(3) + np.array([3.0, -1.0, 0.5])
    for k in range(8):
        steer = tracker.steer(T, FIDUCIALS, live, plan, RigidTransform.identity(), k * 100 * MS,
                              _measured(measured))
    assert (steer.source, steer.fallback, steer.sensor_why_not, steer.limited) == ("sensor", "", "", "")
    entry = steer.T_live_from_ref.apply(ENTRY).reshape(3)
    np.testing.assert_allclose(entry, T.apply(ENTRY).reshape(3), atol=1e-9)
    d_path = steer.T_live_from_ref.R @ (TARGET - ENTRY)
    d_want = measured - entry
    cos = float(d_path @ d_want / np.linalg.norm(d_path) / np.linalg.norm(d_want))
    assert math.degrees(math.acos(min(cos, 1.0))) == pytest.approx(0.0, abs=1e-6)
    assert steer.target_shift_mm == pytest.approx(float(np.linalg.norm(measured - TARGET)), rel=1e-12)


def test_without_a_measurement_the_model_steers_and_says_why_not_the_sensor() -> None:
    plan = _cycle_plan()
    a, b = (TargetTracker(fit_target_model(plan, 2.0, 10.0)) for _ in range(2))
    T = RigidTransform.identity()
    for k in range(6):
        live = FIDUCIALS + (4.0 + k) * UNIT
        plain = a.steer(T, FIDUCIALS, live, plan, T, k * 100 * MS)
        late = b.steer(T, FIDUCIALS, live, plan, T, k * 100 * MS, TargetReading(None, "late"))
        assert late.T_live_from_ref.as_matrix() == pytest.approx(plain.T_live_from_ref.as_matrix(), abs=0.0)
        assert (late.source, late.sensor_why_not, plain.source, plain.sensor_why_not) == (
            "model", "late", "model", "")
    # the markers refused by the model: the measured target still steers; without it, the rigid one
    cough = FIDUCIALS + 6.0 * UNIT + np.array([0.0, 5.0, 0.0])
    by_sensor = b.steer(T, FIDUCIALS, cough, plan, T, 700 * MS, _measured(TARGET + np.array([1.0, 0.0, 0.0])))
    assert (by_sensor.source, by_sensor.fallback) == ("sensor", "")
    kept = a.steer(T, FIDUCIALS, cough, plan, T, 700 * MS, TargetReading(None, "gone"))
    assert (kept.source, kept.sensor_why_not) == ("", "gone")
    assert kept.fallback.startswith("the markers do not move as in the 4D CT")


def test_the_measured_targets_turn_is_held_at_the_bound() -> None:
    plan = _cycle_plan()
    tracker = TargetTracker(fit_target_model(plan, 2.0, 2.0), sensor_max_turn_deg=5.0)
    T = RigidTransform.identity()
    far = TARGET + np.array([0.0, 30.0, 0.0])        # about 21 deg off the planned direction
    steer = tracker.steer(T, FIDUCIALS, FIDUCIALS + 4.0 * UNIT, plan, T, 0, _measured(far))
    assert steer.source == "sensor"
    assert steer.limited.startswith("the sensor's turn ")
    assert steer.limited.endswith(" deg held at the bound 5.0 deg")
    at_entry = tracker.steer(T, FIDUCIALS, FIDUCIALS + 4.0 * UNIT, plan, T, 100 * MS, _measured(ENTRY))
    assert (at_entry.source, at_entry.fallback) == (
        "", "the measured target is 0 mm from the entry (under 1.0 mm): the path has no direction to trust")


class _Log:
    def __init__(self) -> None:
        self.records: list[tuple[str, dict[str, object]]] = []

    def write(self, event: str, **fields: object) -> None:
        self.records.append((event, fields))


def test_the_session_log_says_when_the_path_gains_and_loses_the_sensor() -> None:
    from hil.controller.fsm import State
    from hil.controller.target_model import TargetSteer

    class _Est:
        target_sensor = _sensor()
        target_steer: TargetSteer | None = None

    log = _Log()
    roles = TrackerRoles(None, log)  # type: ignore[arg-type]
    est = _Est()
    T = RigidTransform.identity()
    for source, why, fallback in (("sensor", "", ""), ("sensor", "", ""), ("model", "late", ""),
                                  ("", "gone", "the markers do not move"), ("sensor", "", "")):
        est.target_steer = TargetSteer(T, 1.0, 0.0, 0.0, fallback, source=source, sensor_why_not=why)
        roles.target_sensor(est, State.COMPENSATE)  # type: ignore[arg-type]
    assert log.records == [
        ("target_sensor_in_use", {"sensor": "target", "state": State.COMPENSATE}),
        ("target_sensor_lost", {"sensor": "target", "state": State.COMPENSATE, "reason": "late",
                                "instead": "the model's target"}),
        ("target_sensor_in_use", {"sensor": "target", "state": State.COMPENSATE})]


CONFIG = Path("configs/sim_patient.toml")


def test_a_target_sensor_needs_the_surrogate_model_and_a_tracker_that_has_it() -> None:
    with pytest.raises(ValueError, match=r"target_sensor needs compensation.target_model = \"surrogate\""):
        ProcedureConfig.model_validate({"tracking": {"target_sensor": "target"}})
    setup = load_setup(CONFIG)
    assert target_sensor_problem(setup) is None
    proc = ProcedureConfig.model_validate({"tracking": {"target_sensor": "tumour"},
                                           "compensation": {"target_model": "surrogate"}})
    wrong = setup.model_copy(update={"procedure": proc})
    assert target_sensor_problem(wrong) == ("procedure.tracking.target_sensor = 'tumour': the tracker has no "
                                            "such sensor (its sensors: reference, needle, target)")
    assert target_sensor_problem(wrong.model_copy(update={"tracker": None})) == (
        "procedure.tracking.target_sensor = 'tumour' needs a tracker: the setup has no [tracker]")


def test_hil_run_refuses_a_target_sensor_the_tracker_does_not_have(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from hil.cli import main

    cal = (Path("configs") / "calibration" / "sim_stereo.json").resolve()
    text = CONFIG.read_text().replace('stereo = "calibration/sim_stereo.json"', f'stereo = "{cal}"')
    text = text.replace("[procedure.tracking]\n", '[procedure.tracking]\ntarget_sensor = "tumour"\n')
    cfg = tmp_path / "tumour.toml"
    cfg.write_text(text + '\n[procedure.compensation]\ntarget_model = "surrogate"\n')
    assert main(["run", str(cfg), "--auto", "--session-dir", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert ("target_sensor = 'tumour': the tracker has no such sensor (its sensors: reference, needle, "
            "target)") in err


def _sensor_setup(tmp_path: Path, seed: int, sensor: str | None) -> tuple[Any, Any]:
    cal = (Path("configs") / "calibration" / "sim_stereo.json").resolve()
    text = CONFIG.read_text().replace('stereo = "calibration/sim_stereo.json"', f'stereo = "{cal}"')
    if sensor is not None:
        text = text.replace("[procedure.tracking]\n", f'[procedure.tracking]\ntarget_sensor = "{sensor}"\n')
    cfg = tmp_path / f"sensor_{sensor}.toml"
    cfg.write_text(text + '\n[procedure.compensation]\ntarget_model = "surrogate"\n')
    setup = load_setup(cfg)
    setup = setup.model_copy(update={"simulation": setup.simulation.model_copy(update={"seed": seed})})
    return setup, plan_from_dict(four_d_ct_plan(setup.simulation), "ct")


@pytest.mark.slow
def test_a_procedure_locks_on_the_sensors_target_where_the_model_cannot_see_the_hold(tmp_path: Path) -> None:
    """Seed 4's lock breath-hold leaves the target where no skin marker shows (the simulator's
    breath-hold reproducibility): the model's path misses the true target at lock by 2.0 mm, the
    sensor's by 0.55 mm; every pair pointed at the sensor's target and the log says so once."""
    errors = {}
    for sensor in (None, "target"):
        setup, plan = _sensor_setup(tmp_path, 4, sensor)
        s = run_procedure(CONFIG, setup, plan, auto=True, session_dir=tmp_path / f"s_{sensor}",
                          max_duration_s=40.0)
        assert s.final_state == "done"
        assert s.target_error_mm is not None
        errors[sensor] = s.target_error_mm
        log = list(read_session_log(s.session_log))
        steps = [r for r in log if r["event"] == "compensation_step"]
        assert steps
        assert load_session(Path(s.session_log)).target_sensor_fraction() == s.target_sensor_fraction
        if sensor is None:
            assert s.target_sensor_fraction is None
            assert not any("target_source" in r for r in steps)
            continue
        assert s.target_sensor_fraction == 1.0
        assert {r["target_source"] for r in steps} == {"sensor"}
        said = [r["event"] for r in log if r["event"].startswith("target_sensor_")]
        assert said == ["target_sensor_in_use"]
    assert errors[None] > 1.5        # the bound on the target at lock
    assert errors["target"] < 1.0
