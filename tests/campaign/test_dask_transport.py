"""The transport tier through the Dask executor: one real-time run (serial silence while
compensating: the real ``fob`` driver against ``tools/trackersim``) on a 1-worker LocalCluster on
loopback; the worker starts the run's emulator itself and sends the run's files back (~40 s)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.campaign.executor import DaskExecutor
from hil.campaign.transport import select_transport
from hil.campaign.transport_tasks import run_transport_matrix

pytestmark = [pytest.mark.emulator, pytest.mark.slow]


def test_a_transport_run_on_a_dask_worker_starts_its_own_emulator(tmp_path: Path) -> None:
    with DaskExecutor(workers=1) as ex:
        summary = run_transport_matrix(select_transport(["serial_silence@compensate"]), [1], out_dir=tmp_path,
                                       executor=ex, keep_logs=True, timeout_s=100.0)
    (rec,) = summary["results"]
    assert (rec["run_id"], rec["tier"], rec["attempts"]) == ("serial_silence@compensate_s1", "transport", 1)
    assert rec["passed"] is True, rec["reasons"]
    assert (rec["state_at_onset"], rec["outcome"], rec["final_state"]) == ("compensate", "safe_state", "done")
    assert rec["replay"] == "hil campaign --transport serial_silence@compensate --seed 1"
    assert summary["executor"] == {"kind": "dask", "scheduler": "LocalCluster", "workers": 1}
    # the worker's run directory came back: the mixed setup points the fob driver at the pty of the
    # emulator the worker started, whose log is there too
    run_dir = tmp_path / "logs" / "serial_silence@compensate_s1"
    assert 'driver = "fob"\nport = "/dev/pts/' in (run_dir / "setup.toml").read_text()
    assert (run_dir / "trackersim.log").is_file()
    assert rec["session_log"] == str(tmp_path / "logs" / "serial_silence@compensate_s1.jsonl")
    assert json.loads((tmp_path / "transport.json").read_text())["runs"] == 1
