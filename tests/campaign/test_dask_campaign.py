"""The simulator tier gives the same verdict for every run under both executors: a small matrix
(baseline, a camera fault while compensating, a robot fault at the gate; seed 1) on the local
executor (2 processes) and on a 2-worker Dask LocalCluster on loopback - and again as two shards
(``--shard 0/2``, ``1/2``) merged with ``hil campaign merge``. ~2 minutes on 2 cores."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hil.campaign.campaign import run_campaign
from hil.campaign.executor import DaskExecutor, LocalExecutor
from hil.campaign.scenarios import select
from hil.cli import main
from hil.config import default_setup_path

SCENARIOS = ["frame_drop@compensate", "protective_stop@gate"]
#: What a run's verdict is (everything the simulator determines; not wall times, hosts, log digests).
VERDICT = ("run_id", "scenario", "passed", "outcome", "reasons", "onset_s", "state_at_onset", "detected_s",
           "safe_state", "safe_latency_ms", "stop_latency_ms", "recovered_to_lock", "final_state",
           "lock_error_mm", "commands", "limit_violations", "log_ok", "state_windows_s", "duration_s")

pytestmark = pytest.mark.slow


def _verdicts(summary: dict[str, Any]) -> list[dict[str, Any]]:
    return [{k: r.get(k) for k in VERDICT} for r in summary["results"]]


@pytest.fixture(scope="module")
def local_summary(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    with LocalExecutor(2) as ex:
        return run_campaign(select(SCENARIOS), [1], config=default_setup_path(), plan=None, executor=ex,
                            out_dir=tmp_path_factory.mktemp("local"), timeout_s=110.0)


@pytest.fixture(scope="module")
def dask_cluster() -> Iterator[DaskExecutor]:
    ex = DaskExecutor(workers=2)
    try:
        yield ex
    finally:
        ex.close()


def test_both_executors_give_the_same_verdicts(
    local_summary: dict[str, Any], dask_cluster: DaskExecutor, tmp_path: Path
) -> None:
    dask_summary = run_campaign(select(SCENARIOS), [1], config=default_setup_path(), plan=None,
                                executor=dask_cluster, out_dir=tmp_path, timeout_s=110.0)
    assert [r["run_id"] for r in local_summary["results"]] == [
        "baseline_s1", "frame_drop@compensate_s1", "protective_stop@gate_s1"]
    assert _verdicts(dask_summary) == _verdicts(local_summary)
    assert dask_summary["executor"] == {"kind": "dask", "scheduler": "LocalCluster", "workers": 2}
    assert local_summary["executor"] == {"kind": "local", "workers": 2}
    for key in ("runs", "passed", "failed", "worst_safe_latency_ms", "code_version", "config_sha256",
                "matrix"):
        assert dask_summary[key] == local_summary[key], key
    assert all(r["attempts"] == 1 for r in dask_summary["results"])
    assert all(len(r["session_log_sha256"]) == 64 for r in dask_summary["results"])


def test_two_shards_merged_equal_the_whole_matrix(
    local_summary: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dirs = [tmp_path / "shard0", tmp_path / "shard1"]
    codes = [main(["campaign", *SCENARIOS, "--shard", f"{i}/2", "--jobs", "2", "--timeout", "110",
                   "--out", str(d), "--json"]) for i, d in enumerate(dirs)]
    first, second = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert [r["run_id"] for r in first["results"]] == ["baseline_s1", "protective_stop@gate_s1"]
    assert [r["run_id"] for r in second["results"]] == ["frame_drop@compensate_s1"]
    assert (first["shard"], second["shard"]) == ({"index": 0, "count": 2}, {"index": 1, "count": 2})
    merged_code = main(["campaign", "merge", *map(str, dirs), "--out", str(tmp_path / "all"), "--json"])
    merged = json.loads(capsys.readouterr().out)
    assert _verdicts(merged) == _verdicts(local_summary)
    assert merged["matrix"] == local_summary["matrix"]
    expected = 0 if local_summary["failed"] == 0 else 1
    assert merged_code == expected
    assert codes == [0 if first["failed"] == 0 else 1, 0 if second["failed"] == 0 else 1]
