"""The single-slice stereotaxy (seed 004 §IV) as the controller's image -> robot registration (the
CT-Bot route, ``[procedure.registration] robot_method = "stereotaxy"``): spots and frame files made
from the simulator's truth, the run locks as with the flange-marker route (docs/pose004.md section 8)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from hil.cli.cmd_run import run_procedure
from hil.config import load_setup
from hil.config.setup import SetupConfig
from hil.controller.config import ProcedureConfig, RegistrationConfig
from hil.controller.metrics import RunSummary
from hil.controller.plan_file import load_plan
from hil.geometry.stereotaxy import Rod, StereotacticFrame, predict_spots
from hil.geometry.transform import RigidTransform

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "sim.toml"
PLAN = ROOT / "configs" / "plans" / "sim_plan.json"
PIXEL = (0.5, 0.5)


def _cube(side_mm: float = 80.0) -> StereotacticFrame:
    h, e = side_mm / 2, 0.375 * side_mm
    return StereotacticFrame("cube", (
        Rod("A_vertical", np.array([-h, -e, -h]), np.array([-h, -e, h])),
        Rod("A_diagonal", np.array([-h, -e, -h]), np.array([-h, e, h])),
        Rod("B_vertical", np.array([-e, h, -h]), np.array([-e, h, h])),
        Rod("B_diagonal", np.array([-e, h, -h]), np.array([e, h, h])),
        Rod("C_vertical", np.array([h, e, -h]), np.array([h, e, h])),
        Rod("C_diagonal", np.array([h, e, -h]), np.array([h, -e, h])),
    ))


def _events(summary: RunSummary) -> list[dict[str, Any]]:
    return [json.loads(line) for line in Path(summary.session_log).read_text().splitlines()]


def _truth_robot_from_image(setup: SetupConfig) -> RigidTransform:
    sim = setup.simulation
    assert sim is not None
    return sim.T_optical_from_robot.as_transform().inverse() @ sim.patient.T_optical_from_image.as_transform()


def _stereotaxy_setup(tmp_path: Path, setup: SetupConfig, *, spot_noise_px: float = 0.0,
                      max_residual_mm: float = 1.0) -> SetupConfig:
    """Frame and spots files in ``tmp_path`` consistent with the simulator's truth: the robot held
    the cube frame (mounted at ``T_tcp_from_frame``) so that the slice z = 0 cuts it near the plan's
    entry point; its TCP pose at scan time follows from the truth."""
    frame = _cube()
    (tmp_path / "frame.json").write_text(json.dumps({
        "schema": "hil.stereotactic_frame", "version": 1, "name": frame.name,
        "rods": [{"id": r.rod_id, "start_mm": r.start_mm.tolist(), "end_mm": r.end_mm.tolist()}
                 for r in frame.rods]}))
    entry = load_plan(PLAN).entry_mm.reshape(3)
    T_scanner_from_frame = RigidTransform.from_rotvec([0.05, -0.1, 0.3], [entry[0], entry[1], 0.0])
    T_tcp_from_frame = RigidTransform.from_rotvec([0.0, 0.0, 0.4], [10.0, -5.0, 120.0])
    T_robot_from_tcp = (_truth_robot_from_image(setup) @ T_scanner_from_frame @ T_tcp_from_frame.inverse())
    pred = predict_spots(frame, T_scanner_from_frame, PIXEL)
    assert all(p.on_rod and p.uv_px is not None for p in pred)
    rng = np.random.default_rng(5)
    spots = [{"rod": p.rod_id, "u_px": p.uv_px[0] + spot_noise_px * rng.normal(),
              "v_px": p.uv_px[1] + spot_noise_px * rng.normal()} for p in pred if p.uv_px is not None]
    (tmp_path / "spots.json").write_text(json.dumps({
        "schema": "hil.ct_slice_spots", "version": 1, "pixel_mm": list(PIXEL), "spots": spots}))
    proc = setup.procedure.model_dump()
    proc["registration"]["robot_method"] = "stereotaxy"
    proc["registration"]["stereotaxy"] = {
        "spots": tmp_path / "spots.json", "frame": tmp_path / "frame.json",
        "max_residual_mm": max_residual_mm,
        "robot_tcp_at_scan": (*T_robot_from_tcp.t, *T_robot_from_tcp.as_rotvec()),
        "tcp_from_frame": (*T_tcp_from_frame.t, *T_tcp_from_frame.as_rotvec())}
    return setup.model_copy(update={"procedure": ProcedureConfig.model_validate(proc)})


def _run(tmp_path: Path, setup: SetupConfig, max_duration_s: float | None = None) -> RunSummary:
    return run_procedure(CONFIG, setup, load_plan(PLAN), auto=True, session_dir=tmp_path,
                         max_duration_s=max_duration_s)


@pytest.fixture(scope="module")
def flange_route(tmp_path_factory: pytest.TempPathFactory) -> RunSummary:
    return _run(tmp_path_factory.mktemp("flange"), load_setup(CONFIG))


@pytest.mark.parametrize("noise_px", [0.0, 0.25])
def test_stereotaxy_route_locks_like_the_flange_route(tmp_path: Path, flange_route: RunSummary,
                                                      noise_px: float) -> None:
    setup = _stereotaxy_setup(tmp_path, load_setup(CONFIG), spot_noise_px=noise_px)
    s = _run(tmp_path, setup)
    assert s.final_state == "done"
    assert flange_route.final_state == "done"
    assert s.lock_error_mm is not None
    assert flange_route.lock_error_mm is not None
    assert s.lock_error_mm < 0.5
    assert s.lock_error_mm < flange_route.lock_error_mm + (0.1 if noise_px == 0 else 0.4)
    done = next(e for e in _events(s) if e["event"] == "registration_done")
    assert done["robot_method"] == "stereotaxy"
    assert done["robot_residual_mm"] < (1e-6 if noise_px == 0 else 0.3)
    flange_done = next(e for e in _events(flange_route) if e["event"] == "registration_done")
    assert flange_done["robot_method"] == "flange_markers"
    # the composed T_robot_from_optical maps the entry point (seen by the camera) where the truth does
    d = done["T_robot_from_optical"]
    T_est = RigidTransform.from_rotvec(d["rotvec_rad"], d["t_mm"])
    sim = load_setup(CONFIG).simulation
    assert sim is not None
    T_true = sim.T_optical_from_robot.as_transform().inverse()
    entry_optical = sim.patient.T_optical_from_image.as_transform().apply(load_plan(PLAN).entry_mm)
    err_mm = float(np.linalg.norm(T_est.apply(entry_optical) - T_true.apply(entry_optical)))
    assert err_mm < (0.15 if noise_px == 0 else 0.6)

def test_a_bad_slice_fails_the_registration(tmp_path: Path) -> None:
    setup = _stereotaxy_setup(tmp_path, load_setup(CONFIG), spot_noise_px=20.0, max_residual_mm=0.5)
    s = _run(tmp_path, setup, max_duration_s=8.0)
    assert "plan" not in s.states
    failed = [e for e in _events(s) if e["event"] == "registration_failed"]
    assert failed
    assert "stereotaxy residual" in failed[0]["reason"]


def test_missing_files_fail_the_registration_with_the_path(tmp_path: Path) -> None:
    setup = _stereotaxy_setup(tmp_path, load_setup(CONFIG))
    (tmp_path / "spots.json").unlink()
    s = _run(tmp_path, setup, max_duration_s=8.0)
    failed = [e for e in _events(s) if e["event"] == "registration_failed"]
    assert failed
    assert "spots.json" in failed[0]["reason"]
    assert "not found" in failed[0]["reason"]


def test_robot_method_defaults_to_flange_markers_and_is_validated() -> None:
    assert RegistrationConfig().robot_method == "flange_markers"
    with pytest.raises(ValidationError, match="stereotaxy"):
        RegistrationConfig.model_validate({"robot_method": "stereotaxy"})
    with pytest.raises(ValidationError):
        RegistrationConfig.model_validate({"robot_method": "ct"})
    cfg = RegistrationConfig.model_validate(
        {"robot_method": "stereotaxy", "stereotaxy": {"spots": "s.json", "frame": "f.json",
                                                      "robot_tcp_at_scan": [0, 0, 0, 0, 0, math.pi / 2]}},
        context={"config_dir": "/data"})
    assert cfg.stereotaxy is not None
    assert str(cfg.stereotaxy.spots) == "/data/s.json"
