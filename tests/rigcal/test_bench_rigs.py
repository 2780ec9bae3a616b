"""``tools/bench accuracy --rigs N`` (issue 43): two rigs end to end on the local executor (the
JSON's keys, the worst rig rerun alone by its printed command gives the same figure), a refused
calibration and a hung rig counted with their reasons, a worker on other code refused, the
summary's arithmetic, and bad input (a missing plan in both modes too) one line with exit 2.

The rigs run a shortened rig calibration (8 poses, 2 temporal cycles) to keep the tests short."""

from __future__ import annotations

import json
import shlex
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from hil.rigcal.draw import RigTolerances, draw_rig
from hil.rigcal.fleet import execute_rig_task, rig_task, summarize
from tests.benchtools import load_bench
from tests.rigcal.conftest import CONFIGS

PLAN = CONFIGS / "plans" / "sim_realistic_plan.json"
KEYS = {"rigs", "lock_err_mm_p50_calibrated", "lock_err_mm_p95_calibrated", "lock_err_mm_p99_calibrated",
        "lock_err_mm_p50_cad", "lock_err_mm_p95_cad", "lock_err_mm_p99_cad", "refused", "refused_reasons",
        "crashed", "crashed_reasons", "worst", "per_rig", "executor", "tolerances"}


def _bench() -> ModuleType:
    return load_bench("bench_accuracy", "bench_accuracy_under_test")


def _config(tmp_path: Path, extra: str = "") -> Path:
    """sim_realistic.toml with a short rig calibration (and ``extra`` in ``[rig_calibration]``)."""
    text = (CONFIGS / "sim_realistic.toml").read_text()
    cal = (CONFIGS / "calibration" / "sim_stereo.json").resolve()
    text = text.replace('stereo = "calibration/sim_stereo.json"', f'stereo = "{cal}"')
    text += (f"\n[rig_calibration]\nposes = 8\nmin_poses = 6\n{extra}\n"
             "[rig_calibration.temporal]\ncycles = 2.0\n")
    cfg = tmp_path / "short.toml"
    cfg.write_text(text)
    return cfg


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, dict[str, Any] | None, str]:
    code = _bench().main(argv)
    out = capsys.readouterr()
    return code, (json.loads(out.out) if code == 0 and "--json" in argv else None), out.err


def test_two_rigs_and_the_worst_reruns_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _config(tmp_path)
    code, out, err = _run(["--config", str(cfg), "--plan", str(PLAN), "--rigs", "2", "--first-seed", "4",
                           "--workers", "2", "--json"], capsys)
    assert code == 0, err
    assert out is not None
    assert set(out) >= KEYS
    assert out["rigs"] == 2
    assert out["refused"] == 0
    assert out["refused_reasons"] == {}
    assert out["crashed"] == 0
    assert out["executor"] == {"kind": "local", "workers": 2}
    assert [r["seed"] for r in out["per_rig"]] == [4, 5]
    assert err.count("rig-000") == 2  # one progress line per rig on stderr
    cal = [r["lock_err_mm_calibrated"] for r in out["per_rig"]]
    assert all(isinstance(x, float) for x in cal)
    worst = out["worst"]
    assert worst["lock_err_mm_calibrated"] == max(cal) == out["lock_err_mm_max_calibrated"]
    p50, p95, p99 = (out[f"lock_err_mm_{q}_calibrated"] for q in ("p50", "p95", "p99"))
    assert min(cal) <= p50 <= p95 <= p99 <= max(cal)
    k = worst["seed"]
    assert worst["draw"] == json.loads(draw_rig(k, RigTolerances()).model_dump_json())
    argv = shlex.split(worst["rerun"])
    assert argv[:2] == ["tools/bench", "accuracy"]
    assert argv[2:] == ["--config", str(cfg), "--plan", str(PLAN), "--rigs", "1", "--first-seed", str(k),
                        "--json"]
    code, again, err = _run(argv[2:], capsys)
    assert code == 0, err
    assert again is not None
    assert again["rigs"] == 1
    assert again["worst"]["draw"] == worst["draw"]
    assert again["lock_err_mm_p95_calibrated"] == worst["lock_err_mm_calibrated"]
    assert again["worst"]["lock_err_mm_cad"] == worst["lock_err_mm_cad"]


def test_a_refused_calibration_is_counted_with_its_reason(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _config(tmp_path, "max_validation_mm = 0.001")
    code, out, err = _run(["--config", str(cfg), "--plan", str(PLAN), "--rigs", "1", "--first-seed", "2",
                           "--workers", "1", "--json"], capsys)
    assert code == 0, err
    assert out is not None
    assert out["refused"] == 1
    (reason,) = out["refused_reasons"]
    assert reason.startswith("RigCalibrationError: ")
    assert "max_validation_mm" in reason
    assert out["lock_err_mm_p95_calibrated"] is None
    assert out["locked_cad"] == 1
    assert out["worst"]["by"] == "lock_err_mm_cad"
    assert out["per_rig"][0]["outcome"] == "refused"


def test_a_hung_rig_is_counted_not_raised(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(["--config", str(_config(tmp_path)), "--plan", str(PLAN), "--rigs", "1",
                           "--rig-timeout-s", "0.5", "--json"], capsys)
    assert code == 0, err
    assert out is not None
    assert out["crashed"] == 1
    assert out["crashed_reasons"] == {"after 2 attempts: rig did not finish within 0.5 s (hang)": 1}
    assert out["worst"] is None
    assert out["per_rig"][0]["attempts"] == 2
    assert "running it once more" in err


def test_a_worker_on_other_code_runs_nothing(tmp_path: Path) -> None:
    cfg = _config(tmp_path)
    task = rig_task(cfg, PLAN, RigTolerances(), 3, replay="x")
    other = type(task)(**{**task.__dict__, "code_version": "git:0000000"})
    rec = execute_rig_task(other).record
    assert rec["outcome"] == "error"
    assert rec["reasons"][0].endswith("the bench git:0000000")
    assert "rig" not in rec


def _rec(seed: int, outcome: str, cad: float | None, cal: float | None, reasons: list[str] | None = None,
         ) -> dict[str, Any]:
    rig = None if outcome in ("hang", "crashed") else {
        "draw": {"seed": seed}, "calibration": {"layout_mm_rms": 0.01 * seed},
        "cad": {"final_state": "done" if cad is not None else "aborted", "lock_error_mm": cad},
        "calibrated": None if outcome == "refused" else {"final_state": "done", "lock_error_mm": cal}}
    return {"seed": seed, "outcome": outcome, "reasons": reasons or [], "rig": rig}


def test_summary_arithmetic() -> None:
    recs = [_rec(1, "calibrated", 1.0, 0.2), _rec(2, "calibrated", None, 0.4), _rec(3, "refused", 2.0, None,
            ["RigCalibrationError: too few poses"]), _rec(4, "hang", None, None, ["after 2 attempts: hang"]),
            _rec(5, "calibrated", 3.0, 0.3)]
    out = summarize(recs, {k: f"rerun {k}" for k in range(1, 6)})
    assert out["rigs"] == 5
    assert out["lock_err_mm_p50_calibrated"] == pytest.approx(0.3)
    assert out["lock_err_mm_p95_calibrated"] == pytest.approx(0.39)
    assert out["lock_err_mm_p99_calibrated"] == pytest.approx(0.398)
    assert out["lock_err_mm_p95_cad"] == pytest.approx(2.9)
    assert (out["locked_cad"], out["locked_calibrated"], out["not_locked_cad"]) == (3, 3, 1)
    assert (out["done_cad"], out["done_calibrated"]) == (3, 3)
    assert out["refused"] == 1
    assert out["refused_reasons"] == {"RigCalibrationError: too few poses": 1}
    assert out["crashed"] == 1
    assert out["crashed_reasons"] == {"after 2 attempts: hang": 1}
    assert out["worst"] == {"seed": 2, "by": "lock_err_mm_calibrated", "lock_err_mm_calibrated": 0.4,
                            "lock_err_mm_cad": None, "draw": {"seed": 2}, "rerun": "rerun 2"}


@pytest.mark.parametrize(("args", "message"), [
    (["--rigs", "0"], "--rigs must be >= 1"),
    (["--rigs", "2", "--workers", "0"], "--workers must be >= 1"),
    (["--rigs", "2", "--trace", "x.csv"], "--rigs runs every rig CAD and calibrated"),
])
def test_bad_arguments_exit_2(args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        _bench().main(args)
    assert info.value.code == 2
    assert message in capsys.readouterr().err


def test_a_setup_with_real_devices_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    cfg = CONFIGS / "sim_ursim.toml"   # the UR driver (against tools/ursim): not a drawn rig's
    code = _bench().main(["--config", str(cfg), "--plan", str(PLAN), "--rigs", "1"])
    err = capsys.readouterr().err
    assert code == 2
    assert err == (f"tools/bench accuracy: error: {cfg}: drawn rigs run on a simulated setup only (every "
                   "device's driver simulated, [simulation] real_time = false)\n")


@pytest.mark.parametrize(("args", "message"), [
    (["--tolerances", "/nonexistent/tol.toml"],
     "tools/bench accuracy: error: /nonexistent/tol.toml: cannot read"),
    (["--scheduler", "tcp://127.0.0.1:1"],
     "tools/bench accuracy: error: --scheduler applies to --executor dask only"),
])
def test_bad_input_is_one_line(args: list[str], message: str, tmp_path: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    code = _bench().main(["--config", str(_config(tmp_path)), "--plan", str(PLAN), "--rigs", "1", *args])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(message)
    assert err.count("\n") == 1



def test_rigs_run_on_a_dask_local_cluster(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # the rig's bound is too short for a rig: the Dask worker runs the task, kills the rig's process,
    # the executor retries it once; what comes back is the record, as on the local executor
    args = ["--rigs", "1", "--executor", "dask", "--workers", "1", "--rig-timeout-s", "0.5", "--json"]
    code, out, err = _run(["--config", str(_config(tmp_path)), "--plan", str(PLAN), *args], capsys)
    assert code == 0, err
    assert out is not None
    assert out["executor"] == {"kind": "dask", "scheduler": "LocalCluster", "workers": 1}
    assert out["crashed_reasons"] == {"after 2 attempts: rig did not finish within 0.5 s (hang)": 1}


@pytest.mark.parametrize("mode", [["--runs", "1"], ["--rigs", "1"]])
def test_a_missing_plan_is_one_line(mode: list[str], tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "no_plan_beside.toml"     # its bundled plan, plans/no_plan_beside_plan.json, is absent
    cfg.write_text((CONFIGS / "sim_realistic.toml").read_text())
    code = _bench().main(["--config", str(cfg), *mode])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"tools/bench accuracy: error: {tmp_path / 'plans' / 'no_plan_beside_plan.json'}: "
                          "cannot read plan")
    assert err.count("\n") == 1
