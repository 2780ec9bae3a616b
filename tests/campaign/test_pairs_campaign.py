"""A small compound-fault campaign through the CLI, end to end (``hil campaign --pairs``): the
baseline, the single-fault run a recovery scenario is placed from, an overlapping pair on two
devices and one on the same device, and a second fault during the recovery. Seed 1, 2 processes,
~2 minutes on 2 cores."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from hil.cli import main

OVERLAP = "frame_drop+robot_disconnect@compensate"
SAME_DEVICE = "frame_drop+stale_timestamp@lock"
RECOVERY = "robot_disconnect+tracker_timeout@compensate+recovery"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("pairs")
    code = main(["campaign", "--pairs", OVERLAP, SAME_DEVICE, RECOVERY, "--seed", "1", "--jobs", "2",
                 "--out", str(out), "--timeout", "150"])
    return code, json.loads((out / "campaign.json").read_text()), out


def test_every_run_passes(campaign: tuple[int, dict[str, Any], Path]) -> None:
    code, summary, _ = campaign
    assert summary["failing"] == []
    assert (code, summary["runs"], summary["passed"], summary["limit_violations"]) == (0, 5, 5, 0)
    assert summary["pairs"] == {"runs": 3, "overlapping": 2, "recovery": 1, "passed": 3}
    assert [r["run_id"] for r in summary["results"]] == [
        "baseline_s1", "robot_disconnect@compensate_s1",
        f"{OVERLAP}_s1", f"{SAME_DEVICE}_s1", f"{RECOVERY}_s1"]


def test_overlapping_faults_both_hit_the_state_and_end_safe(
        campaign: tuple[int, dict[str, Any], Path]) -> None:
    _, summary, _ = campaign
    runs = {r["scenario"]: r for r in summary["results"]}
    r = runs[OVERLAP]
    assert (r["kind"], r["second_kind"]) == ("frame_drop", "robot_disconnect")
    assert (r["state_at_onset"], r["second_state_at_onset"]) == ("compensate", "compensate")
    assert r["second_onset_s"] == pytest.approx(r["onset_s"] + 0.05)
    assert (r["outcome"], r["safe_state"], r["recovered_to_lock"], r["final_state"]) == (
        "safe_state", "fault", True, "done")
    # the robot fault, 50 ms after the frame drop, is due within the robot's bound (183.333 ms) of
    # its own onset, not the camera's (650 ms): the supervisor reads the robot while the camera is
    # silent. Before it ticked on its own clock the safe state came 386 ms after the frame drop.
    assert r["latency_bound_ms"] == 233.333
    assert 0 <= r["safe_latency_ms"] <= r["latency_bound_ms"]
    assert r["inputs"]["second_kind"] == "robot_disconnect"
    assert r["replay"].startswith(f"hil campaign --pairs {OVERLAP} --seed 1 ")


def test_two_faults_on_one_device(campaign: tuple[int, dict[str, Any], Path]) -> None:
    _, summary, _ = campaign
    r = {r["scenario"]: r for r in summary["results"]}[SAME_DEVICE]
    assert (r["state_at_onset"], r["second_kind"], r["outcome"], r["final_state"]) == (
        "lock", "stale_timestamp", "safe_state", "done")
    assert r["latency_bound_ms"] == 650.0  # both camera faults: the camera's bound from the first
    assert 0 <= r["safe_latency_ms"] <= r["latency_bound_ms"]


def test_second_fault_lands_in_the_recovery_and_ends_safe(campaign: tuple[int, dict[str, Any], Path]) -> None:
    _, summary, _ = campaign
    runs = {r["scenario"]: r for r in summary["results"]}
    single = runs["robot_disconnect@compensate"]
    enter_s, leave_s, state = single["recovery_window_s"]
    r = runs[RECOVERY]
    assert state == "approach"
    assert enter_s <= r["second_onset_s"] < leave_s
    assert r["second_onset_s"] == r["inputs"]["second_start_s"]
    assert (r["second_state_at_onset"], r["second_safe_state"]) == ("approach", "fault")
    assert 0 <= r["second_safe_latency_ms"] <= r["second_latency_bound_ms"]
    assert (r["recovered_to_lock"], r["final_state"]) == (True, "done")
    # identical to the single-fault run until the second fault: same first fault, same safe state
    assert (r["onset_s"], r["safe_latency_ms"]) == (single["onset_s"], single["safe_latency_ms"])


def test_files_and_table(campaign: tuple[int, dict[str, Any], Path]) -> None:
    _, _, out = campaign
    page = (out / "campaign.html").read_text()
    assert "<th>second fault</th>" in page
    assert "robot_disconnect+tracker_timeout+recovery" in page
    assert not (out / "logs").exists()
