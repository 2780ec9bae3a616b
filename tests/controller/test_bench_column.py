"""``tools/bench accuracy``'s column figures from its seeds' records (``_column``): the arithmetic of
each figure on two hand-made seeds, one locked and one that faulted, exactly."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from tests.benchtools import load_bench

CONFIG = Path("configs/sim.toml")
PLAN = Path("configs/plans/sim_plan.json").resolve()


def _bench() -> ModuleType:
    return load_bench("bench_accuracy", "bench_accuracy_column")


def _records() -> list[dict[str, Any]]:
    locked = {"seed": 1, "final_state": "done", "lock_error_mm": 0.3, "lock_direction_error_deg": 0.1,
              "time_to_lock_s": 7.0, "gate_open_fraction": 0.5, "target_error_mm": 1.0,
              "entry_axis_error_mm": 0.2, "body_rigid_residual_mm_p95": 2.0, "change_fre_mm_p95": 0.5,
              "gate_false_open_rate": 0.25, "gate_open_ticks": 40}
    faulted = {"seed": 2, "final_state": "fault", "lock_error_mm": None, "lock_direction_error_deg": None,
               "time_to_lock_s": None, "gate_open_fraction": 0.0, "target_error_mm": None,
               "entry_axis_error_mm": None, "body_rigid_residual_mm_p95": 3.0, "change_fre_mm_p95": None,
               "gate_false_open_rate": None, "gate_open_ticks": 0}
    return [locked, faulted]


def _follow(guide: list[float], axis_entry: list[float], **path: list[float]) -> dict[str, list[float]]:
    """The following run's series (``FOLLOW_SERIES``): the given ones, the rest empty."""
    out: dict[str, list[float]] = {name: [] for name in _bench().FOLLOW_SERIES}
    out.update(guide=guide, axis_entry=axis_entry, **path)
    return out


def test_a_column_from_a_locked_and_a_faulted_seed() -> None:
    runs = _records()
    nan = math.nan
    follow = _follow([1.0, 2.0, 3.0, 4.0], [0.5, 1.5], path_pair=[nan, 1.0, 2.0, 3.0],
                     path_now=[nan, 2.0, 3.0, 4.0], path_entry=[nan, 0.1, 0.2, 0.3],
                     path_direction=[nan, 1.0, 1.0, 1.0])
    out = _bench()._column(runs, comp_all=[0.1, 0.2], hold_targets=[0.4, 0.6], follow=follow,
                           follow_model=[(0.1, 0.0, 0.5), (0.3, 0.2, 0.75)], hold_entries=[0.1, 0.2, 0.2])
    assert out["runs"] == 2
    assert out["runs_done"] == 1
    # only the locked seed has lock figures
    assert out["lock_err_mm_mean"] == pytest.approx(0.3)
    assert out["lock_err_mm_rms"] == pytest.approx(0.3)
    assert out["lock_err_mm_max"] == 0.3
    assert out["dir_err_deg_rms"] == pytest.approx(0.1)
    assert out["target_err_mm_p95"] == pytest.approx(1.0)
    assert out["entry_axis_err_mm_rms"] == pytest.approx(0.2)
    assert out["entry_axis_err_hold_mm_rms"] == pytest.approx(math.sqrt(0.03))   # every LOCK sample
    # the following run's samples give the compensation p95; the hold's stand beside it
    assert out["comp_err_mm_p95"] == pytest.approx(3.85)
    assert out["comp_err_mm_rms_following"] == pytest.approx(math.sqrt(7.5))
    assert out["comp_entry_err_mm_p95_following"] == pytest.approx(1.45)
    # the path's split: p95 over the samples that had a path (NaN: none yet)
    assert out["follow_path_pair_mm_p95"] == pytest.approx(2.9)
    assert out["follow_path_now_mm_p95"] == pytest.approx(3.9)
    assert out["follow_path_entry_mm_p95"] == pytest.approx(0.29)
    assert out["follow_path_direction_deg_p95"] == pytest.approx(1.0)
    assert out["target_model_fallback_fraction_following"] == pytest.approx(0.2)
    assert out["target_model_held_fraction_following"] == pytest.approx(0.1)
    assert out["target_sensor_fraction_following"] == pytest.approx(0.625)
    assert out["comp_err_mm_p95_hold"] == pytest.approx(0.195)
    assert out["target_err_hold_mm_p95"] == pytest.approx(0.59)
    # every seed with the figure counts: the faulted one's residual too
    assert out["body_rigid_residual_mm_p95"] == pytest.approx(2.95)
    assert out["change_fre_mm_p95"] == pytest.approx(0.5)
    # false opens weigh by open ticks: 10 of 40 (the faulted seed never opened)
    assert out["gate_false_open_rate"] == pytest.approx(0.25)
    assert out["gate_open_fraction_mean"] == pytest.approx(0.25)
    assert out["time_to_lock_s_median"] == 7.0
    assert out["per_run"] is runs


def test_the_following_error_seed_by_seed() -> None:
    """Each seed's own p95 beside the pooled one: median, the worst and its seed, how many over
    1 mm; a seed without a following run (``--follow-s 0``) is left out."""
    runs = [{**r, "seed": seed, "follow_guide_mm_p95": p95}
            for r, (seed, p95) in zip(_records() * 2, [(1, 0.5), (2, 1.2), (3, 0.8), (4, None)], strict=True)]
    out = _bench()._column(runs, comp_all=[], hold_targets=[], follow=_follow([1.0], [0.5]),
                           follow_model=[], hold_entries=[])
    assert out["follow_guide_mm_p95_seed_median"] == pytest.approx(0.8)
    assert out["follow_guide_mm_p95_seed_max"] == 1.2
    assert out["follow_guide_mm_p95_worst_seed"] == 2
    assert out["follow_guide_seeds_over_1mm"] == 1
    assert _bench()._per_seed_row(out) == "0.80/1.20 (s2)"


def test_without_a_following_run_the_hold_gives_the_compensation_figure() -> None:
    out = _bench()._column(_records(), comp_all=[0.1, 0.2], hold_targets=[], follow=_follow([], []),
                           follow_model=[], hold_entries=[])
    assert out["comp_err_mm_p95"] == pytest.approx(0.195)
    assert out["comp_err_mm_rms_following"] is None
    assert out["comp_entry_err_mm_p95_following"] is None
    assert out["target_model_fallback_fraction_following"] is None
    assert out["target_model_held_fraction_following"] is None
    assert out["follow_path_pair_mm_p95"] is None
    assert out["follow_guide_mm_p95_seed_max"] is None
    assert out["follow_guide_seeds_over_1mm"] == 0
    assert _bench()._per_seed_row(out) == "n/a"
    assert out["target_err_hold_mm_p95"] is None
    assert out["entry_axis_err_hold_mm_rms"] is None


def test_no_seed_locked_leaves_the_lock_figures_empty() -> None:
    out = _bench()._column(_records()[1:], comp_all=[], hold_targets=[], follow=_follow([], []),
                           follow_model=[], hold_entries=[])
    assert out["runs_done"] == 0
    for key in ("lock_err_mm_mean", "lock_err_mm_rms", "lock_err_mm_max", "dir_err_deg_rms",
                "comp_err_mm_p95", "target_err_mm_p95", "target_err_mm_max", "entry_axis_err_mm_rms",
                "gate_false_open_rate", "time_to_lock_s_median", "change_fre_mm_p95"):
        assert out[key] is None, key


def test_a_calibration_file_missing_is_one_line_not_a_traceback(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """The stereo calibration is read when the devices open (the first seed's), after the setup
    and the plan were read: still one line naming the file, exit 2."""
    cfg = tmp_path / "sim.toml"
    cfg.write_text(CONFIG.read_text())        # configs/sim.toml beside no calibration/ directory
    code = _bench().main(["--config", str(cfg), "--plan", str(PLAN), "--runs", "1", "--follow-s", "0",
                          "--json"])
    err = capsys.readouterr().err
    assert code == 2
    missing = tmp_path / "calibration" / "sim_stereo.json"
    assert err == f"tools/bench accuracy: error: {missing}: calibration file not found\n"


@pytest.mark.parametrize("noise", ["-0.1", "nan", "10"])
def test_a_ct_noise_out_of_range_is_a_usage_error(noise: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        _bench().main(["--ct-noise-mm", noise, "--json"])
    assert exc.value.code == 2
    assert "--ct-noise-mm must be >= 0 and < 10 mm" in capsys.readouterr().err


def test_the_seeds_4d_ct_carries_the_asked_localisation_error() -> None:
    """``--ct-noise-mm`` reaches the simulated 4D CT each seed gets: 0 gives the body's own phases,
    the default the module's 0.3 mm draws."""
    bench = _bench()
    from drivers.sim.planning_ct import DEFAULT_CT_NOISE_MM, four_d_ct_phases
    from hil.config import load_setup
    from hil.controller.plan_file import load_plan

    base = load_setup(Path("configs/sim_patient.toml"))
    comp = base.procedure.compensation.model_copy(update={"target_model": "surrogate"})
    setup = base.model_copy(update={"procedure": base.procedure.model_copy(update={"compensation": comp})})
    plan = load_plan(Path("configs/plans/sim_patient_plan.json"))
    for noise in (0.0, DEFAULT_CT_NOISE_MM):
        got = bench._with_4d_ct(plan, setup, noise)
        want = four_d_ct_phases(setup.simulation, noise_mm=noise)
        assert [p.fiducials_mm.tolist() for p in got.phases] == [w["fiducials_mm"] for w in want]
        assert [p.entry_mm.tolist() for p in got.phases] == [w["entry_mm"] for w in want]
    exact = bench._with_4d_ct(plan, setup, 0.0)
    noisy = bench._with_4d_ct(plan, setup)
    assert exact.phases[0].fiducials_mm.tolist() != noisy.phases[0].fiducials_mm.tolist()


def test_one_seed_s_own_following_p95_is_the_pooled_one(capsys: pytest.CaptureFixture[str]) -> None:
    """Through the bench's loop: the following run's p95 lands in the seed's record, and with one
    seed the per-seed figures and the pooled p95 are the same samples' figure."""
    code = _bench().main(["--config", str(CONFIG), "--plan", str(PLAN), "--runs", "1", "--follow-s", "3",
                          "--no-rig-calibration", "--json"])
    assert code == 0
    col = json.loads(capsys.readouterr().out)   # one column: the config has no rig errors
    own = col["per_run"][0]["follow_guide_mm_p95"]
    assert isinstance(own, float)
    assert own > 0.0
    assert own == col["comp_err_mm_p95"] == col["follow_guide_mm_p95_seed_max"]
    assert col["follow_guide_mm_p95_worst_seed"] == 1
