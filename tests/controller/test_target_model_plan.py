"""The surrogate target model from the user's side (issue 41 point 2): a plan's 4D CT phases read
and refused with the field named, the simulated planning 4D CT (drivers/sim/planning_ct.py) and
its tool, ``hil run`` refusing the model without phases, and a simulated procedure steering by it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.sim.body import body_from_config
from drivers.sim.motion import PatientMotion
from drivers.sim.planning_ct import four_d_ct, four_d_ct_phases, four_d_ct_plan
from drivers.sim.world import phantom_from_config
from hil.cli import main
from hil.cli.cmd_run import run_procedure
from hil.config import load_setup
from hil.config.body import BodyTraceConfig
from hil.config.simulation import SimulationConfig
from hil.controller.plan_file import load_plan, plan_from_dict
from hil.controller.target_model import fit_target_model
from hil.errors import InputFileError
from hil.session import read_session_log
from tests.benchtools import load_bench

CONFIG = Path("configs/sim_patient.toml")
REPO = Path(__file__).resolve().parents[2]


def _doc(**extra: Any) -> dict[str, Any]:
    doc = json.loads(Path("configs/plans/sim_patient_plan.json").read_text())
    doc.update(extra)
    return doc


def test_a_plan_with_phases_reads_them_in_order() -> None:
    fid = np.asarray(_doc()["fiducials_mm"])
    phases = [{"fiducials_mm": (fid + k).tolist(), "target_mm": [1.0 * k, 2.0, 3.0]} for k in (1, 2)]
    plan = plan_from_dict(_doc(phases=phases), "p.json")
    assert len(plan.phases) == 2
    np.testing.assert_array_equal(plan.phases[1].fiducials_mm, fid + 2)
    np.testing.assert_array_equal(plan.phases[1].target_mm, [2.0, 2.0, 3.0])
    assert plan.phases[1].entry_mm is None
    assert plan_from_dict(_doc(), "p.json").phases == ()


def test_a_phase_may_give_the_entry() -> None:
    fid = np.asarray(_doc()["fiducials_mm"])
    phases = [{"fiducials_mm": (fid + k).tolist(), "target_mm": [1.0 * k, 2.0, 3.0],
               "entry_mm": [0.5 * k, 0.0, 1.0]} for k in (1, 2)]
    plan = plan_from_dict(_doc(phases=phases), "p.json")
    entry = plan.phases[1].entry_mm
    assert entry is not None
    np.testing.assert_array_equal(entry, [1.0, 0.0, 1.0])


@pytest.mark.parametrize(("phases", "message"), [
    ({"a": 1}, "p.json: phases: must be a list of {fiducials_mm, target_mm}"),
    ([{"fiducials_mm": [[0, 0, 0]] * 6}],
     "p.json: phases[0]: must be an object with fiducials_mm, target_mm and optionally entry_mm"),
    ([{"fiducials_mm": [[0, 0, 0]] * 6, "target_mm": [0, 0, 0], "entry_mm": [0, 0]}],
     "p.json: phases[0].entry_mm: "),
    ([{"fiducials_mm": [[0, 0, 0]] * 6, "target_mm": [0, 0, 0], "entry_mm": [0, 0, 0]},
      {"fiducials_mm": [[0, 0, 0]] * 6, "target_mm": [0, 0, 0]}],
     "p.json: phases[1]: no entry_mm, where other phases give one (in every phase or in none)"),
    ([{"fiducials_mm": [[0, 0, 0]] * 5, "target_mm": [0, 0, 0]}],
     "p.json: phases[0].fiducials_mm: 5 points, the plan has 6 fiducials"),
    ([{"fiducials_mm": [[0, 0, 0]] * 6, "target_mm": [0, 0]}], "p.json: phases[0].target_mm: "),
    ([{"fiducials_mm": [[0, 0, 0]] * 6, "target_mm": [0, 0, 0], "extra": 1}], "p.json: phases[0]: must be"),
])
def test_bad_phases_name_the_phase_and_field(phases: Any, message: str) -> None:
    with pytest.raises(InputFileError) as info:
        plan_from_dict(_doc(phases=phases), "p.json")
    assert str(info.value).startswith(message)


@pytest.mark.parametrize(("period", "with_phases", "message"), [
    (0.1, True, "p.json: phases_period_s: a breathing period in s, 0.5-30 (got 0.1)"),
    ("4", True, "p.json: phases_period_s: a breathing period in s, 0.5-30 (got '4')"),
    (True, True, "p.json: phases_period_s: a breathing period in s, 0.5-30 (got True)"),
    (4.0, False, "p.json: phases_period_s: given without phases"),
])
def test_a_bad_ct_period_is_named(period: Any, with_phases: bool, message: str) -> None:
    fid = _doc()["fiducials_mm"]
    phases = [{"fiducials_mm": fid, "target_mm": [0.0, 0.0, 0.0]}] if with_phases else []
    with pytest.raises(InputFileError) as info:
        plan_from_dict(_doc(phases=phases, phases_period_s=period), "p.json")
    assert str(info.value) == message


def test_the_simulated_4d_ct_is_the_seeds_and_fits_the_model() -> None:
    sim = load_setup(CONFIG).simulation.model_copy(update={"seed": 4})
    a, b = four_d_ct_phases(sim), four_d_ct_phases(sim)
    assert a == b                                              # seeded: the same CT for the seed
    assert len(a) == 9
    other = four_d_ct_phases(sim.model_copy(update={"seed": 5}))
    assert other != a
    plan = plan_from_dict(four_d_ct_plan(sim), "ct")
    m = fit_target_model(plan, 2.0, 10.0)
    assert plan.phases_period_s == sim.breathing.period_s
    assert m.explained > 0.9                                   # one pattern carries the skin's breathing
    peak = max(float(np.linalg.norm(p.target_mm - plan.target_mm)) for p in plan.phases)
    assert 10.0 < peak < 13.0                                  # [simulation.body.target] amplitude 12 mm
    # what the line misses is the target's lag and hysteresis, well under its excursion
    assert m.fit_residual_mm < 0.2 * peak


def test_a_rigid_phantom_has_no_simulated_4d_ct() -> None:
    rigid = load_setup(Path("configs/sim.toml")).simulation
    with pytest.raises(ValueError, match="a 4D CT of a rigid phantom"):
        four_d_ct_phases(rigid)


def _traced(tmp_path: Path, period_s: float) -> SimulationConfig:
    """sim_patient driven by a 200 s surrogate trace breathing ``period_s`` (end-exhale at 0 s)."""
    t = np.arange(0.0, 200.0, 0.1)
    trace = tmp_path / "resp.txt"
    trace.write_text("".join(f"{a:.3f} {-math.cos(2 * math.pi * a / period_s):.9f}\n" for a in t))
    sim = load_setup(CONFIG).simulation
    return sim.model_copy(update={"body": sim.body.model_copy(update={"trace": BodyTraceConfig(
        path=trace, start_s=0.0, rate_hz=10.0)})})


def test_a_traced_patients_4d_ct_is_sorted_from_the_breaths_before_the_start(tmp_path: Path) -> None:
    sim = _traced(tmp_path, 4.0)
    ct = four_d_ct(sim, noise_mm=0.0)
    assert ct.period_s == pytest.approx(4.0, abs=0.03)
    assert len(ct.phases) == 9
    # every breath alike: each phase is the body at that fraction of one breath after an end-exhale
    # (before the start the world wraps to the trace's end, its last sample at 199.9 s: world time
    # -39.9 s is the trace's 160 s, an end-exhale)
    world_body = body_from_config(sim, phantom_from_config(sim.patient), PatientMotion(sim))
    assert world_body is not None
    for k, phase in enumerate(ct.phases, start=1):
        want = world_body.state(-39.9 + 4.0 * k / 10)
        np.testing.assert_allclose(phase["entry_mm"], want.entry_mm, atol=0.05)
        np.testing.assert_allclose(phase["target_mm"], want.target_mm, atol=0.05)
        np.testing.assert_allclose(phase["fiducials_mm"], want.markers_mm, atol=0.05)
    plan = plan_from_dict(four_d_ct_plan(sim), "ct")
    assert plan.phases_period_s == pytest.approx(4.0, abs=0.03)
    assert fit_target_model(plan, 2.0, 10.0).explained > 0.9


def test_a_trace_without_three_breaths_before_the_start_has_no_4d_ct(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"^a 4D CT of the trace needs 3 whole breaths in the 60 s before "
                                         r"the start; it has 1$"):
        four_d_ct(_traced(tmp_path, 20.0))


def test_the_tool_writes_a_plan_hil_reads(tmp_path: Path) -> None:
    out = tmp_path / "ct.json"
    done = subprocess.run([sys.executable, str(REPO / "tools" / "planning" / "sim4dct.py"), str(CONFIG),
                           "--out", str(out), "--seed", "3", "--phases", "6"],
                          capture_output=True, text=True, cwd=REPO, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout == (f"{out}: plan of the simulated patient (seed 3) with 5 phases after the "
                           "registered one\n")
    assert len(load_plan(out).phases) == 5
    bad = subprocess.run([sys.executable, str(REPO / "tools" / "planning" / "sim4dct.py"), "configs/sim.toml",
                          "--out", str(tmp_path / "x.json")],
                         capture_output=True, text=True, cwd=REPO, timeout=120, check=False)
    assert bad.returncode == 2
    assert bad.stderr == ("tools/sim4dct: error: a 4D CT of a rigid phantom: [simulation.body] model is "
                          "'rigid'\n")


def _surrogate_config(tmp_path: Path) -> Path:
    cal = (REPO / "configs" / "calibration" / "sim_stereo.json").resolve()
    text = CONFIG.read_text().replace('stereo = "calibration/sim_stereo.json"', f'stereo = "{cal}"')
    cfg = tmp_path / "surrogate.toml"
    cfg.write_text(text + '\n[procedure.compensation]\ntarget_model = "surrogate"\n')
    return cfg


def test_hil_run_refuses_the_model_without_a_4d_ct(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(_surrogate_config(tmp_path)), "--plan", "configs/plans/sim_patient_plan.json",
                 "--auto", "--session-dir", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 2
    assert err == ("hil run: error: configs/plans/sim_patient_plan.json: the surrogate target model needs a "
                   "4D CT: >= 2 breathing phases in the plan's 'phases', it has 0\n")


@pytest.mark.slow
def test_a_procedure_steers_by_the_model_and_says_so(tmp_path: Path) -> None:
    setup = load_setup(_surrogate_config(tmp_path))
    setup = setup.model_copy(update={"simulation": setup.simulation.model_copy(update={"seed": 2})})
    plan = plan_from_dict(four_d_ct_plan(setup.simulation), "ct")
    s = run_procedure(CONFIG, setup, plan, auto=True, session_dir=tmp_path / "s", max_duration_s=30.0)
    assert s.final_state == "done"
    log = list(read_session_log(s.session_log))
    reg = [r for r in log if r["event"] == "registration_done"]
    assert reg
    assert reg[-1]["target_model"]["explained"] > 0.9
    steps = [r for r in log if r["event"] == "compensation_step"]
    assert steps
    for r in steps:
        assert {"target_score_mm", "target_shift_mm", "target_turn_deg", "target_fallback",
                "target_limited"} <= r.keys()
        assert 0.0 <= r["target_turn_deg"] <= setup.procedure.compensation.target_model_max_turn_deg
        if r["target_fallback"] == "":
            assert math.isfinite(r["target_score_mm"])
        else:
            assert r["target_shift_mm"] == 0.0


def _bench_module() -> Any:
    return load_bench("bench_accuracy", "bench_accuracy_for_target_model")


@pytest.mark.slow
def test_following_free_breathing_the_path_follows_the_modelled_target(tmp_path: Path) -> None:
    """The bench's free-breathing run (the gate opens at once, 12 s of compensation): steering by
    the 4D CT's model brings the guide closer to the ideal stand-off point on the true moving path
    than the rigid direction does, on the same seed and the same breathing; the entry is the
    estimator's either way."""
    bench = _bench_module()
    base = load_setup(_surrogate_config(tmp_path))
    sim = base.simulation.model_copy(update={"seed": 3, "breathing": base.simulation.breathing.model_copy(
        update=bench.BENCH_BREATHING)})
    plan = plan_from_dict(four_d_ct_plan(sim), "ct")
    figures = {}
    for model in ("rigid", "surrogate"):
        comp = base.procedure.compensation.model_copy(update={"target_model": model})
        setup = base.model_copy(update={"simulation": sim, "procedure": base.procedure.model_copy(
            update={"compensation": comp})})
        follow, shares = bench._follow_run(CONFIG, setup, plan, tmp_path / model, 12.0)
        path, entry = follow["guide"], follow["axis_entry"]
        assert len(path) > 100
        assert (shares is None) == (model == "rigid")
        if shares is not None:
            assert shares[0] < 0.5           # the model steered most pairs of the free breathing
        figures[model] = (float(np.percentile(path, 95)), float(np.percentile(entry, 95)))
    assert figures["surrogate"][0] < 0.7 * figures["rigid"][0], figures
    assert figures["surrogate"][1] == pytest.approx(figures["rigid"][1], abs=0.3), figures
