"""The loop's predictor in simulated procedures (simulated devices, real vision, ManualClock):
``predictor = "alpha-beta"`` is today's controller to the last bit, and a learning predictor's
fallback at a patient shift is said in the session log (docs/prediction.md "In the loop")."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from hil.config import load_setup
from hil.config.setup import SetupConfig
from hil.config.simulation import ShiftConfig
from hil.controller import events as ev
from hil.controller.metrics import RunSummary
from hil.controller.plan_file import load_plan
from hil.geometry import native
from hil.session import read_session_log
from hil.vision import kernel

CONFIG = Path("configs/sim.toml")
PLAN = load_plan("configs/plans/sim_plan.json")

#: ``_following("alpha-beta")``'s figures before issue 42's predictor existed (commit 0be3925, the
#: compiled kernels built; the same seed; the rate limits about the TCP, as then): the alpha-beta
#: path must reproduce them exactly
BEFORE: dict[str, Any] = {
    "final_state": "safe_stop", "fre_mm": 0.016238866263402308, "robot_fre_mm": 0.033003384419303644,
    "comp_error_rms_mm": 0.4320535359268331, "comp_error_p95_mm": 0.6063231926398089,
    "comp_error_max_mm": 2.238514872719053, "latency_ms": {"p50": 30.0, "p95": 30.0},
    "duration_s": 10.019333383000001, "frames": 149, "commands_sent": 58, "commands_refused": 0,
    "comp_target_error_p95_mm": 0.2844900130623888, "comp_entry_error_p95_mm": 0.23811893911937626,
    "change_fre_mm": {"p50": 0.03351181158817505, "p95": 0.05566662517158117}, "gate_open_ticks": 58,
}


def _following(predictor: str, sim: dict[str, Any] | None = None, settle_s: float = 60.0) -> SetupConfig:
    """configs/sim.toml following free breathing (10 mm, 4 s) from the gate on, as tools/bench
    accuracy's following run: the gate opens at once, COMPENSATE never settles."""
    s = load_setup(CONFIG)
    p = s.procedure
    proc = p.model_copy(update={
        "gate": p.gate.model_copy(update={"tolerance_mm": 30.0, "hold_request_s": 0.1,
                                          "min_hold_left_s": None, "moved_after_s": None,
                                          "shape_tolerance_mm": None}),
        "compensation": p.compensation.model_copy(update={"settle_s": settle_s, "predictor": predictor}),
        "lock": p.lock.model_copy(update={"drift_alarm_mm": 30.0}),
    })
    breathing = s.simulation.breathing.model_copy(update={"enabled": True, "amplitude_mm": 10.0,
                                                         "period_s": 4.0})
    simulation = s.simulation.model_copy(update={"breathing": breathing, **(sim or {})})
    return s.model_copy(update={"procedure": proc, "simulation": simulation})


def _run(setup: SetupConfig, tmp_path: Path, max_s: float) -> RunSummary:
    from hil.cli.cmd_run import run_procedure

    return run_procedure(CONFIG, setup, PLAN, auto=True, session_dir=tmp_path, max_duration_s=max_s)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_alpha_beta_is_the_controller_before_the_predictor(tmp_path: Path) -> None:
    # the figures were recorded with the compiled kernels (they agree with numpy to rounding only)
    was_geometry, was_vision = native.use_native(True), kernel.use_kernel(True)
    try:
        assert native.active() is not None, native.native_status()
        setup = _following("alpha-beta")
        comp = setup.procedure.compensation.model_copy(update={"rate_limit_pivot": "tcp"})
        proc = setup.procedure.model_copy(update={"compensation": comp})
        setup = setup.model_copy(update={"procedure": proc})
        s = _run(setup, tmp_path, 10.0)
    finally:
        native.use_native(was_geometry)
        kernel.use_kernel(was_vision)
    got = s.to_dict()
    assert {k: got[k] for k in BEFORE} == BEFORE
    steps = [r for r in read_session_log(s.session_log) if r["event"] == ev.COMPENSATION_STEP]
    assert len(steps) > 50
    assert {r["setpoint_by"] for r in steps} == {"alpha-beta"}
    assert not any(r["event"] == ev.PREDICTOR_FALLBACK for r in read_session_log(s.session_log))


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_shift_while_following_is_said_and_alpha_beta_takes_over(tmp_path: Path) -> None:
    """A 4 mm patient shift at 8 s (COMPENSATE follows from ~6 s, the predictor warm since ~7 s):
    the learning predictor's innovation check fires on a pair after it, the session log says so
    and alpha-beta sets the setpoint for the hold (1 s)."""
    shift = ShiftConfig(at_s=8.0, translation_mm=(4.0, 0.0, 0.0))
    s = _run(_following("ar-ls", {"shifts": (shift,)}), tmp_path, 10.0)
    recs = list(read_session_log(s.session_log))
    falls = [r for r in recs if r["event"] == ev.PREDICTOR_FALLBACK]
    assert len(falls) == 1
    f = falls[0]
    assert (f["predictor"], f["fallback"], f["fallbacks"], f["hold_s"]) == ("ar-ls", "alpha-beta", 1, 1.0)
    assert f["reason"].startswith("innovation ")
    steps = [r for r in recs if r["event"] == ev.COMPENSATION_STEP]
    before = [r for r in steps if r["exposure_t_ns"] < f["exposure_t_ns"]]
    after = [r for r in steps if r["exposure_t_ns"] >= f["exposure_t_ns"]]
    assert before[-1]["setpoint_by"] == "ar-ls"
    hold_ns = 1_000_000_000
    in_hold = [r for r in after if r["exposure_t_ns"] < f["exposure_t_ns"] + hold_ns]
    assert {r["setpoint_by"] for r in in_hold} == {"alpha-beta"}
    assert len(after) > 15
    assert s.commands_refused == 0
