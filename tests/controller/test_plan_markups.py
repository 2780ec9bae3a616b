"""Plans from planning software: 3D Slicer markups and labelled point files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hil.controller.plan_file import load_plan
from hil.errors import InputFileError

PLANS = Path(__file__).resolve().parents[2] / "configs" / "plans"


@pytest.mark.parametrize("name", ["sim_plan.mrk.json", "sim_plan.fcsv"])
def test_slicer_plan_equals_the_project_plan(name: str) -> None:
    ours = load_plan(PLANS / "sim_plan.json")
    slicer = load_plan(PLANS / name)
    np.testing.assert_array_equal(slicer.fiducials_mm, ours.fiducials_mm)
    np.testing.assert_array_equal(slicer.entry_mm, ours.entry_mm)
    np.testing.assert_array_equal(slicer.target_mm, ours.target_mm)
    assert slicer.source == str(PLANS / name)


def test_labelled_csv_plan_roles_by_label_in_any_case_and_order(tmp_path: Path) -> None:
    f = tmp_path / "plan.csv"
    f.write_text("label,x,y,z\nTarget,1,2,-80\nA,0,0,0\nB,50,0,0\nENTRY,1,2,0\nC,0,60,0\n")
    plan = load_plan(f)
    np.testing.assert_array_equal(plan.fiducials_mm, [[0, 0, 0], [50, 0, 0], [0, 60, 0]])
    np.testing.assert_array_equal(plan.entry_mm, [1, 2, 0])
    np.testing.assert_array_equal(plan.target_mm, [1, 2, -80])


def test_slicer_ras_plan_is_converted_to_lps(tmp_path: Path) -> None:
    doc = json.loads((PLANS / "sim_plan.mrk.json").read_text())
    mk = doc["markups"][0]
    mk["coordinateSystem"] = "RAS"
    for cp in mk["controlPoints"]:
        cp["position"] = [-cp["position"][0], -cp["position"][1], cp["position"][2]]
    f = tmp_path / "ras.mrk.json"
    f.write_text(json.dumps(doc))
    np.testing.assert_allclose(load_plan(f).entry_mm, load_plan(PLANS / "sim_plan.json").entry_mm)


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ("A,0,0,0\nB,50,0,0\nC,0,60,0\ntarget,1,2,-80\n", "exactly one point labelled 'entry'; found none"),
        (
            "A,0,0,0\nB,50,0,0\nC,0,60,0\nentry,1,2,0\nentry,1,2,1\ntarget,1,2,-80\n",
            "exactly one point labelled 'entry'; found 2 (points 4, 5)",
        ),
        (
            "A,0,0,0\nB,50,0,0\nentry,1,2,0\ntarget,1,2,-80\n",
            ">= 3 fiducials besides entry and target; found 2",
        ),
        ("A,0,0,0\nB,50,0,0\nC,0,60,0\nentry,1,2,0\ntarget,1,2,0.5\n", "less than 1 mm apart"),
    ],
)
def test_bad_labelled_plans_name_the_file_and_the_problem(tmp_path: Path, rows: str, message: str) -> None:
    f = tmp_path / "plan.csv"
    f.write_text("label,x,y,z\n" + rows)
    with pytest.raises(InputFileError) as err:
        load_plan(f)
    assert err.value.path == str(f)
    assert message in err.value.reason


def test_a_hil_plan_json_without_format_still_says_so(tmp_path: Path) -> None:
    f = tmp_path / "plan.json"
    f.write_text('{"fiducials_mm": [[0,0,0],[1,0,0],[0,1,0]], "entry_mm": [0,0,0], "target_mm": [0,0,9]}')
    with pytest.raises(InputFileError, match="format: expected 'hil-plan'"):
        load_plan(f)


def test_labelled_json_point_list_is_a_plan(tmp_path: Path) -> None:
    f = tmp_path / "plan.json"
    pts = [{"label": "a", "x": 0, "y": 0, "z": 0}, {"label": "b", "x": 50, "y": 0, "z": 0},
           {"label": "c", "x": 0, "y": 60, "z": 0}, {"label": "entry", "x": 1, "y": 2, "z": 0},
           {"label": "target", "x": 1, "y": 2, "z": -80}]
    f.write_text(json.dumps({"points": pts}))
    plan = load_plan(f)
    assert plan.fiducials_mm.shape == (3, 3)
    np.testing.assert_array_equal(plan.target_mm, [1, 2, -80])
