"""Setup configs: every shipped file validates; bad files give one line per problem."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil.config import FaultKind, FaultSpec, default_setup_path, load_setup, parse_setup
from hil.config.faults import FAULT_DEVICE
from hil.config.types import TransformConfig
from hil.errors import ConfigError
from plugins.registry import DriverRegistry
from tests.devices.conftest import CONFIGS

SHIPPED = sorted(CONFIGS.glob("*.toml"))


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "setup.toml"
    p.write_text(text)
    return p


def test_the_shipped_configs_are_the_expected_ones() -> None:
    assert [p.name for p in SHIPPED] == [
        "sim.toml", "sim_faults.toml", "sim_needle.toml", "sim_needle_collinear.toml", "sim_patient.toml",
        "sim_realistic.toml", "sim_ursim.toml",
        "ur3_aravis_aurora.toml", "ur3_aravis_fob.toml", "ur3_v4l2.toml"]


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_config_validates(path: Path, registry: DriverRegistry) -> None:
    setup = load_setup(path, registry)
    assert setup.camera.driver in registry.names("camera")
    assert setup.robot.driver in registry.names("robot")
    assert setup.tracker is None or setup.tracker.driver in registry.names("tracker")


def test_sim_config_is_complete(registry: DriverRegistry) -> None:
    setup = load_setup(CONFIGS / "sim.toml", registry)
    assert (setup.camera.driver, setup.robot.driver, setup.tracker.driver) == ("sim", "sim", "sim")
    assert setup.calibration.stereo == CONFIGS / "calibration" / "sim_stereo.json"
    assert setup.calibration.stereo.is_file()
    assert setup.simulation.seed == 7
    assert setup.safety.motion_limits().max_speed_mm_s == 100.0
    assert setup.config_dir == CONFIGS


def test_sim_patient_is_the_realistic_rig_with_a_deformable_body(registry: DriverRegistry) -> None:
    patient = load_setup(CONFIGS / "sim_patient.toml", registry)
    realistic = load_setup(CONFIGS / "sim_realistic.toml", registry)
    assert patient.simulation.body.model == "deformable"
    assert patient.simulation.body.trace.path is None
    assert patient.simulation.rig_errors == realistic.simulation.rig_errors
    assert patient.simulation.patient == realistic.simulation.patient
    assert patient.simulation.breathing == realistic.simulation.breathing
    # the one procedure key of its own: where its simulated target sensor sits against the target
    sensor = next(s for s in patient.tracker.sensors if s.attached_to == "target")
    offset = patient.procedure.tracking.target_sensor_offset_mm
    assert offset == sensor.T_attached_from_sensor.translation_mm == (4.0, -3.0, 2.0)
    assert patient.procedure.tracking.target_sensor is None
    procedure = patient.procedure.model_copy(update={"tracking": realistic.procedure.tracking})
    assert (patient.camera, patient.robot, procedure) == (realistic.camera, realistic.robot,
                                                          realistic.procedure)
    assert realistic.simulation.body.model == "rigid"


def test_sim_faults_has_one_fault_of_each_kind(registry: DriverRegistry) -> None:
    """One of each device kind (the patient kinds, which the simulated world plays, are the
    campaign's and tests/devices/test_patient_faults.py's)."""
    setup = load_setup(CONFIGS / "sim_faults.toml", registry)
    device_kinds = sorted(k for k in FaultKind if FAULT_DEVICE[k] != "patient")
    assert sorted(f.kind for f in setup.faults) == device_kinds


def test_default_setup_is_the_embedded_sim_toml(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HIL_SETUP", raising=False)
    assert default_setup_path() == CONFIGS / "sim.toml"
    monkeypatch.setenv("HIL_SETUP", "/x/y.toml")
    assert default_setup_path() == Path("/x/y.toml")


@pytest.mark.parametrize("name", ["sim", "sim_faults", "sim_realistic", "sim_patient"])
def test_bundled_plan_matches_the_simulated_phantom(name: str, registry: DriverRegistry) -> None:
    """configs/plans/<setup>_plan.json is the CT plan of that setup's simulated phantom."""
    from drivers.sim.world import phantom_from_config

    setup = load_setup(CONFIGS / f"{name}.toml", registry)
    plan = json.loads((CONFIGS / "plans" / f"{name}_plan.json").read_text())
    ph = phantom_from_config(setup.simulation.patient)
    assert plan["frame"] == "image"
    np.testing.assert_allclose(plan["fiducials_mm"], ph.markers_mm, atol=1e-4)
    np.testing.assert_allclose(plan["entry_mm"], ph.entry_mm, atol=1e-4)
    np.testing.assert_allclose(plan["target_mm"], ph.target_mm, atol=1e-4)


def test_bad_config_gives_one_line_per_problem(tmp_path: Path, registry: DriverRegistry) -> None:
    path = _write(tmp_path, """
[camera]
driver = "sim"
fps = 3
[robot]
driver = "nope"
[safety]
max_speed_mm_s = -1
workspace_min_mm = [1.0, 2.0]
[bogus]
x = 1
[[faults]]
kind = "glare"
start_s = 1
duration_s = 0
""")
    with pytest.raises(ConfigError) as info:
        load_setup(path, registry)
    assert info.value.problems == [
        "camera.fps: unknown key",
        f"robot.driver: unknown robot driver 'nope'; known: {registry.names('robot')}",
        "safety.workspace_min_mm: too few values (item 2 missing)",
        "safety.max_speed_mm_s: Input should be greater than 0",
        "faults[0].duration_s: Input should be greater than 0",
        "bogus: unknown key",
    ]
    assert str(info.value).splitlines()[0] == f"{path}: camera.fps: unknown key"


def test_missing_sections_and_driver(tmp_path: Path, registry: DriverRegistry) -> None:
    path = _write(tmp_path, "[camera]\nframe_rate_hz = 3\n")
    with pytest.raises(ConfigError) as info:
        load_setup(path, registry)
    assert info.value.problems == [
        f"camera.driver: required key missing (one of {registry.names('camera')})",
        "robot: required section missing",
    ]


def test_cross_section_problems(tmp_path: Path, registry: DriverRegistry) -> None:
    path = _write(tmp_path, """
[camera]
driver = "sim"
[robot]
driver = "sim"
[safety]
workspace_min_mm = [0.0, 0.0, 0.0]
workspace_max_mm = [0.0, 1.0, 1.0]
[[faults]]
kind = "bad_quality"
start_s = 0
duration_s = 1
lag_ms = 4
[[faults]]
kind = "tracker_timeout"
start_s = 0
duration_s = 1
""")
    with pytest.raises(ConfigError) as info:
        load_setup(path, registry)
    assert info.value.problems == [
        "safety: workspace x: min 0.0 must be below max 0.0",
        "faults[0]: ['lag_ms'] do not apply to a bad_quality fault (it takes ['quality', 'sensors'])",
    ]


def test_fault_needing_a_tracker_without_one(tmp_path: Path, registry: DriverRegistry) -> None:
    path = _write(tmp_path, """
[camera]
driver = "sim"
[robot]
driver = "sim"
[[faults]]
kind = "tracker_timeout"
start_s = 0
duration_s = 1
""")
    with pytest.raises(ConfigError) as info:
        load_setup(path, registry)
    assert info.value.problems == ["faults[0].kind: tracker_timeout needs a [tracker] section"]


def test_not_toml_and_missing_file(tmp_path: Path, registry: DriverRegistry) -> None:
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_setup(_write(tmp_path, "[camera\n"), registry)
    with pytest.raises(ConfigError, match="cannot read"):
        load_setup(tmp_path / "absent.toml", registry)


def test_relative_paths_resolve_against_the_config_file(tmp_path: Path, registry: DriverRegistry) -> None:
    sub = tmp_path / "rig"
    sub.mkdir()
    p = sub / "setup.toml"
    p.write_text('[camera]\ndriver = "sim"\n[robot]\ndriver = "sim"\n[calibration]\nstereo = "cal/s.json"\n')
    setup = load_setup(p, registry)
    assert setup.calibration.stereo == sub / "cal" / "s.json"
    assert setup.config_dir == sub


def test_transform_forms() -> None:
    a = TransformConfig(translation_mm=(1.0, 2.0, 3.0), rotvec_rad=(0.0, 0.0, math.pi / 2))
    m = TransformConfig(matrix=tuple(map(tuple, a.as_transform().as_matrix().tolist())))  # type: ignore[arg-type]
    assert a.as_transform().is_close(m.as_transform(), atol_mm=1e-9, atol_rad=1e-9)
    with pytest.raises(ValueError, match="either matrix or"):
        TransformConfig(translation_mm=(0.0, 0.0, 0.0), matrix=m.matrix)
    with pytest.raises(ValueError, match=r"rotation|orthonormal|proper"):
        TransformConfig(matrix=((2.0, 0, 0, 0), (0, 1.0, 0, 0), (0, 0, 1.0, 0), (0, 0, 0, 1.0)))


def test_setup_is_frozen(registry: DriverRegistry) -> None:
    setup = parse_setup({"camera": {"driver": "sim"}, "robot": {"driver": "sim"}}, source="m",
                        config_dir=Path("."), registry=registry)
    with pytest.raises(ValueError, match="frozen"):
        setup.name = "x"  # type: ignore[misc]


def test_fault_window() -> None:
    f = FaultSpec(kind=FaultKind.FRAME_DROP, start_s=1.0, duration_s=0.5)
    assert (f.active(0.99), f.active(1.0), f.active(1.49), f.active(1.5)) == (False, True, True, False)
    assert f.device == "camera"


def test_docs_hold_the_generated_reference(registry: DriverRegistry) -> None:
    """docs/config.md holds the generated tables of the setup and simulated-driver models verbatim,
    and names every key of the other drivers' and the procedure's models."""
    from pydantic import BaseModel

    from hil.config.reference import config_reference_markdown
    from hil.controller.config import ProcedureConfig

    text = (CONFIGS.parent / "docs" / "config.md").read_text()
    stale = "docs/config.md is stale: run python -m hil.config.reference"
    tables = config_reference_markdown(registry).split("### ")
    own = [t for t in tables if t and "[procedure" not in t.split("\n")[0]
           and ("driver = " not in t.split("\n")[0] or '"sim"' in t.split("\n")[0])]
    for table in own:
        assert f"### {table.strip()}" in text, stale
    others: list[type[BaseModel]] = [d.config_model for d in registry.drivers() if not d.simulated]
    others += [ProcedureConfig] + [f.annotation for f in ProcedureConfig.model_fields.values()
                                   if isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel)]
    missing = sorted({k for m in others for k in m.model_fields if f"`{k}`" not in text})
    assert missing == [], stale


def test_clock_for_the_setup(registry: DriverRegistry) -> None:
    from hil.clock import ManualClock, MonotonicClock
    from hil.config import clock_for

    sim = load_setup(CONFIGS / "sim.toml", registry)
    assert isinstance(clock_for(sim, registry), ManualClock)
    rt = sim.model_copy(update={"simulation": sim.simulation.model_copy(update={"real_time": True})})
    assert isinstance(clock_for(rt, registry), MonotonicClock)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_config_builds_its_devices(path: Path, registry: DriverRegistry) -> None:
    """The registry's factories build every role (CONFIGURED, nothing opened or connected)."""
    from drivers.interfaces import DeviceState
    from hil.clock import ManualClock
    from hil.config import build_devices

    setup = load_setup(path, registry)
    devices = build_devices(setup, ManualClock(), registry)
    try:
        assert all(d.state is DeviceState.CONFIGURED for d in devices)
        assert (devices.tracker is None) == (setup.tracker is None)
        sim = {r for r, c in setup.device_sections().items() if registry.get(r, c.driver).simulated}
        assert (devices.world is None) == (not sim)
    finally:
        devices.close_all()  # a mixed setup's world follows the robot from a thread until it is closed


def test_model_copy_keeps_the_config_dir(registry: DriverRegistry) -> None:
    setup = load_setup(CONFIGS / "sim.toml", registry)
    copy = setup.model_copy(update={"name": "x"})
    assert copy.config_dir == CONFIGS


def test_fault_schedule_from_a_scenario_file(tmp_path: Path, registry: DriverRegistry) -> None:
    from hil.config import load_fault_schedule, with_faults

    p = tmp_path / "scenario.toml"
    p.write_text('name = "drop"\n[[faults]]\nkind = "frame_drop"\nstart_s = 1\nduration_s = 2\n')
    faults = load_fault_schedule(p)
    assert faults == (FaultSpec(kind=FaultKind.FRAME_DROP, start_s=1.0, duration_s=2.0),)
    setup = load_setup(CONFIGS / "sim.toml", registry)
    assert with_faults(setup, faults).faults == faults
    no_tracker = setup.model_copy(update={"tracker": None})
    with pytest.raises(ConfigError, match="needs a \\[tracker\\] section"):
        with_faults(no_tracker, (FaultSpec(kind=FaultKind.BAD_QUALITY, start_s=0.0, duration_s=1.0),))
    p.write_text('[[faults]]\nkind = "meteor"\nstart_s = 1\nduration_s = 2\n')
    with pytest.raises(ConfigError) as info:
        load_fault_schedule(p)
    assert info.value.problems[0].startswith("faults[0].kind: Input should be 'frame_drop'")


def test_reference_update_keeps_the_introduction() -> None:
    from hil.config.reference import MARKER, update_document

    assert update_document(f"intro\n{MARKER}\nold tables\n", "new") == f"intro\n{MARKER}\n\nnew\n"
    with pytest.raises(ValueError, match="not found"):
        update_document("no marker", "new")


# ----------------------------------------------------------------------------- hostile values
@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "1e400"])
def test_non_finite_numbers_are_refused(tmp_path: Path, registry: DriverRegistry, value: str) -> None:
    """TOML's inf/nan (and 1e400, which tomllib reads as inf) would pass gt=0 / ge=0 and silently
    turn a watchdog or a fault off; every config model refuses them (STRICT allow_inf_nan=False)."""
    path = _write(tmp_path, f"""
[camera]
driver = "sim"
[robot]
driver = "sim"
[safety]
tracker_max_age_ms = {value}
[[faults]]
kind = "frame_drop"
start_s = {value}
duration_s = 1
""")
    with pytest.raises(ConfigError) as info:
        load_setup(path, registry)
    keys = [p.split(":")[0] for p in info.value.problems]
    assert keys == ["safety.tracker_max_age_ms", "faults[0].start_s"]


def test_watchdog_ages_have_an_upper_bound(tmp_path: Path, registry: DriverRegistry) -> None:
    from hil.config.setup import MAX_ROBOT_STATE_AGE_MS, MAX_WATCHDOG_AGE_MS

    base = '[camera]\ndriver = "sim"\n[robot]\ndriver = "sim"\n[safety]\n'
    ok = (f"camera_frame_max_age_ms = {MAX_WATCHDOG_AGE_MS}\ntracker_max_age_ms = {MAX_WATCHDOG_AGE_MS}\n"
          f"robot_state_max_age_ms = {MAX_ROBOT_STATE_AGE_MS}\n")
    assert load_setup(_write(tmp_path, base + ok), registry).safety.robot_state_max_age_ms == 1000.0
    too_old = (f"camera_frame_max_age_ms = {MAX_WATCHDOG_AGE_MS + 1}\n"
               f"tracker_max_age_ms = {MAX_WATCHDOG_AGE_MS + 1}\n"
               f"robot_state_max_age_ms = {MAX_ROBOT_STATE_AGE_MS + 1}\n")
    with pytest.raises(ConfigError) as info:
        load_setup(_write(tmp_path, base + too_old), registry)
    assert info.value.problems == [
        "safety.camera_frame_max_age_ms: Input should be less than or equal to 2000",
        "safety.tracker_max_age_ms: Input should be less than or equal to 2000",
        "safety.robot_state_max_age_ms: Input should be less than or equal to 1000",
    ]


@pytest.mark.parametrize(("text", "why"), [
    ("a = " + "[" * 100_000, "nested too deeply"),
    ("a = " + "1" * 5000, "Exceeds the limit (4300 digits)"),
], ids=["deep", "huge_int"])
def test_hostile_toml_is_a_config_error(
    tmp_path: Path, registry: DriverRegistry, text: str, why: str
) -> None:
    from hil.config import load_fault_schedule

    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_setup(path, registry)
    assert info.value.path == str(path)
    assert info.value.problems[0].startswith("unusable TOML: ")
    assert why in info.value.problems[0]
    with pytest.raises(ConfigError, match="unusable TOML"):
        load_fault_schedule(path)
