"""The Aurora rows of the transport tier (docs/campaign.md, "Transport tier"): the REAL ``aurora``
driver on ``tools/trackersim --protocol aurora`` (a subprocess on a pty), the patient reference
sensor on handle 0A in use by the procedure.

Two runs in real time (~30 s in all): the device resetting itself while compensating (the driver
used to stay dead after it: the run ended in FAULT) and the reference out of volume while
compensating (tolerated: the procedure goes on with the skin markers, the reference neither stands
in nor is compared while it is out). Plus the matrix rows and the written setup, without emulator.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import pytest

from hil.campaign.emulators import trackersim_command
from hil.campaign.runner import TOLERATED_LOCK_MM
from hil.campaign.transport import (
    AURORA_PROCEDURE_TRACKING,
    BY_NAME,
    FAMILIES,
    _prepare,
    run_transport_one,
    select_transport,
    write_setup,
)
from hil.config import load_setup
from hil.config.faults import FaultKind

AURORA = ("aurora_bad_crc", "aurora_tool_missing", "aurora_out_of_volume", "aurora_reset",
          "aurora_wrong_baud", "aurora_comm_baud")
Runs = dict[str, tuple[dict[str, Any], dict[str, Any]]]


def test_the_aurora_rows_are_in_every_state() -> None:
    assert tuple(f for f in FAMILIES if f.startswith("aurora")) == AURORA
    chosen = select_transport(["aurora"])
    assert [s.name for s in chosen] == [f"{f}@{st}" for f in AURORA
                                        for st in ("register", "approach", "gate", "compensate", "lock")]
    assert {(s.emulator, s.protocol, s.base) for s in chosen} == {("trackersim", "aurora", "sim.toml")}
    rows = {s.family: (s.kind, s.inject, s.clear, s.duration_s) for s in chosen}
    assert rows == {
        "aurora_bad_crc": (FaultKind.CORRUPT_RECORD, "fault bad_crc,p=1", "clear bad_crc", 0.6),
        "aurora_tool_missing": (FaultKind.SENSOR_MISSING, "fault tool_missing,handles=0A",
                                "clear tool_missing", 1.0),
        "aurora_out_of_volume": (FaultKind.SENSOR_MISSING, "fault out_of_volume,handles=0A",
                                 "clear out_of_volume", 1.0),
        "aurora_reset": (FaultKind.TRACKER_TIMEOUT, "fault reset", None, 1.5),
        "aurora_wrong_baud": (FaultKind.TRACKER_TIMEOUT, "fault wrong_baud,baud=9600", "clear wrong_baud",
                              0.6),
        "aurora_comm_baud": (FaultKind.TRACKER_TIMEOUT, "fault comm_baud,baud=57600; fault reset", None, 3.0),
    }
    assert BY_NAME["serial_silence@gate"].protocol == "fob"


def test_the_written_setup_runs_the_aurora_driver_with_the_reference_in_use(tmp_path: Path) -> None:
    path = write_setup(BY_NAME["aurora_reset@lock"], tmp_path, seed=2, tracker_port="/dev/pts/88")
    raw = tomllib.loads(path.read_text())
    assert raw["tracker"] == {"driver": "aurora", "port": "/dev/pts/88", "baud_rate": 115200,
                              "sensors": {"reference": "0A", "needle": "0B"}, "break_as_nul": True,
                              "reset_timeout_s": 2.0, "response_timeout_s": 0.3, "timeout_s": 0.5,
                              "reinit_after_s": 1.0}
    assert raw["procedure"]["tracking"] == {"reference_sensor": "reference"}
    assert path.read_text().endswith(AURORA_PROCEDURE_TRACKING)
    setup = load_setup(path)  # the whole setup validates: driver config, procedure, safety
    assert setup.procedure.tracking.reference_sensor == "reference"
    assert setup.procedure.tracking.reference_backup is True
    assert raw["robot"]["driver"] == "sim"
    assert raw["camera"]["driver"] == "sim"
    assert raw["safety"]["tracker_max_age_ms"] == 1000.0
    assert raw["simulation"]["seed"] == 2


def _events(log: Path, name: str) -> list[dict[str, Any]]:
    return [r for r in (json.loads(line) for line in log.read_text().splitlines()) if r.get("event") == name]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Runs:
    """Each run: (its judged result, the emulator's status after the run)."""
    logs = tmp_path_factory.mktemp("aurora_transport")
    out: Runs = {}
    for name in ("aurora_reset@compensate", "aurora_out_of_volume@compensate"):
        prepared = _prepare(BY_NAME[name], 1, logs)
        try:
            result = run_transport_one(prepared.spec).to_dict()
            assert prepared.spec.tracker_control is not None
            reply = trackersim_command(Path(prepared.spec.tracker_control), "status")
            out[name] = (result, json.loads(reply.removeprefix("ok").strip()))
        finally:
            prepared.stop()  # the emulator, on every path
    return out


@pytest.mark.emulator
@pytest.mark.slow
def test_a_device_reset_while_compensating_is_recovered(
        runs: Runs) -> None:
    r, status = runs["aurora_reset@compensate"]
    assert r["passed"] is True, r
    assert r["state_at_onset"] == "compensate"
    assert (r["outcome"], r["safe_state"]) == ("safe_state", "fault")
    assert 0.0 <= r["safe_latency_ms"] <= r["latency_bound_ms"], r
    assert r["recovered_to_lock"] is True
    assert r["final_state"] == "done"
    assert r["limit_violations"] == []
    assert status["protocol"] == "aurora"
    assert status["faults_fired"]["reset"] == 1
    assert (status["tracking"], status["baud"]) == (False, 9600)  # the driver closed it: TSTOP, COMM back
    faults = _events(Path(r["session_log"]), "fault_detected")
    assert faults
    assert faults[0]["reason"].startswith("tracker: no valid record")


@pytest.mark.emulator
@pytest.mark.slow
def test_the_reference_out_of_volume_while_compensating_is_tolerated(
        runs: Runs) -> None:
    r, status = runs["aurora_out_of_volume@compensate"]
    assert r["passed"] is True, r
    assert r["state_at_onset"] == "compensate"
    assert r["outcome"] == "tolerated"
    assert r["final_state"] == "done"
    assert r["lock_error_mm"] < TOLERATED_LOCK_MM
    assert status["faults_fired"]["out_of_volume"] > 10  # every reply of the window (40 Hz polls)
    log = Path(r["session_log"])
    assert [e["available"] for e in _events(log, "reference_sensor_recorded")] == [True]
    assert _events(log, "reference_in_use") == []  # the markers gave the change: it never stood in
    assert _events(log, "fault_detected") == []  # the needle tool still tracked: no tracker error
