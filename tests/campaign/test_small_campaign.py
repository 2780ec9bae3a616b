"""A small fixed campaign on the simulator, end to end (parallel processes, JSON, HTML):
the baseline, a camera fault and a robot fault while compensating. ~1 minute on 2 cores."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from hil.campaign.campaign import run_campaign
from hil.campaign.scenarios import select
from hil.config import default_setup_path

SCENARIOS = ["frame_drop@compensate", "robot_disconnect@compensate"]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("campaign")
    summary = run_campaign(
        select(SCENARIOS), [1], config=default_setup_path(), plan=None, jobs=2, out_dir=out, timeout_s=110.0
    )
    return summary, out


def test_every_run_passes(campaign: tuple[dict[str, Any], Path]) -> None:
    summary, _ = campaign
    assert summary["failing"] == []
    assert (summary["runs"], summary["passed"], summary["failed"]) == (3, 3, 0)
    assert summary["limit_violations"] == 0


def test_faults_hit_their_state_and_end_safe_then_recover_to_lock(
    campaign: tuple[dict[str, Any], Path],
) -> None:
    summary, _ = campaign
    runs = {r["scenario"]: r for r in summary["results"]}
    assert runs["baseline"]["final_state"] == "done"
    for name in SCENARIOS:
        r = runs[name]
        assert r["state_at_onset"] == "compensate"
        assert (r["outcome"], r["safe_state"]) == ("safe_state", "fault")
        assert 0 <= r["safe_latency_ms"] <= r["latency_bound_ms"]
        assert r["stop_latency_ms"] is not None
        assert (r["recovered_to_lock"], r["final_state"]) == (True, "done")
        assert r["log_ok"] is True
    assert summary["worst_safe_latency_ms"] == max(runs[n]["safe_latency_ms"] for n in SCENARIOS)


def test_files_written(campaign: tuple[dict[str, Any], Path]) -> None:
    _, out = campaign
    on_disk = json.loads((out / "campaign.json").read_text())
    assert {k: on_disk[k] for k in ("runs", "passed", "failed")} == {"runs": 3, "passed": 3, "failed": 0}
    html = (out / "campaign.html").read_text()
    assert "<th>compensate</th>" in html
    assert "frame_drop" in html
    assert not (out / "logs").exists()  # passing runs keep no session log
