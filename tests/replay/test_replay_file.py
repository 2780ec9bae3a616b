"""``hil replay``: a simulated run's recording read back with Rerun's own reader and checked
against the session log exactly; Rerun's CLI verifies the file; analytics are off."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.cli import main
from hil.replay.scene import GUIDE_ARROW_MM, SCALAR_SERIES
from tests.replay.conftest import read_records


@pytest.fixture(scope="module")
def replay(sim_session: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    import contextlib
    import io

    out = tmp_path_factory.mktemp("rrd") / "run.rrd"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["replay", str(sim_session), "--out", str(out), "--json"])
    assert code == 0
    return out, json.loads(buf.getvalue())


def _rows(rrd: Path) -> dict[str, list[dict[str, Any]]]:
    """entity path -> its rows (record seq, session_time ns, component columns), from Rerun's
    RrdReader, sorted by record seq."""
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        cols = {n: batch.column(n) for n in names if n != "rerun.controls.RowId"}
        for i in range(batch.num_rows):
            row: dict[str, Any] = {"static": chunk.is_static}
            for n, col in cols.items():
                if n == "session_time":
                    row[n] = col.cast("int64")[i].as_py()
                elif n != "log_time":
                    row[n] = col[i].as_py()
            rows[chunk.entity_path.lstrip("/")].append(row)
    for v in rows.values():
        v.sort(key=lambda r: r.get("record", -1))
    return rows


def _f32(rows: list[list[float]]) -> list[list[float]]:
    return np.asarray(rows, dtype=np.float32).tolist()  # type: ignore[no-any-return]


def _expected_scalars(recs: list[dict[str, Any]]) -> dict[str, list[tuple[int, int, float]]]:
    t0 = recs[0]["t_ns"]
    out: dict[str, list[tuple[int, int, float]]] = defaultdict(list)
    for r in recs:
        for event, name, entity in SCALAR_SERIES:
            x = r.get(name)
            if r["event"] == event and isinstance(x, int | float) and not isinstance(x, bool) \
                    and math.isfinite(x):
                out[entity].append((r["seq"], r["t_ns"] - t0, float(x)))
    return out


def test_json_names_the_file_entities_and_timelines(replay: tuple[Path, dict[str, Any]]) -> None:
    out, doc = replay
    assert doc["path"] == str(out)
    assert doc["bytes"] == out.stat().st_size > 0
    assert doc["timelines"] == ["record", "session_time"]
    assert doc["verified"] is True
    assert doc["reason"] == ""
    rows = _rows(out)
    assert set(doc["entities"]) == set(rows) - {"__properties"}


def test_scalar_series_match_the_log_exactly(sim_session: Path, replay: tuple[Path, dict[str, Any]]) -> None:
    recs = read_records(sim_session)
    rows = _rows(replay[0])
    expected = _expected_scalars(recs)
    assert expected["series/following/guide_error_mm"]  # the run measured it
    assert expected["series/latency/detect_ms"]
    assert expected["series/gate/deviation_rms_mm"]
    assert expected["series/servo/longest_interval_ms"]
    assert expected["series/truth/position_error_mm"]
    for entity, samples in expected.items():
        got = [(r["record"], r["session_time"], r["Scalars:scalars"][0]) for r in rows[entity]]
        assert got == samples, entity
    logged_series = {e for e in rows if e.startswith("series/")}
    assert logged_series == set(expected)


def test_points_and_axes_match_the_log(sim_session: Path, replay: tuple[Path, dict[str, Any]]) -> None:
    recs = read_records(sim_session)
    rows = _rows(replay[0])
    frames = [r for r in recs if r["event"] == "frame_measured"]
    seen = [r for r in frames if any(None not in p for p in (r["live_mm"] or []))]
    assert [r["record"] for r in rows["world/skin/seen"]] == [r["seq"] for r in seen]
    first = seen[0]
    got = rows["world/skin/seen"][0]["Points3D:positions"]
    want = [p for p in first["live_mm"] if None not in p]
    assert _f32(got) == _f32(want)  # Points3D stores float32: exactly the log's values rounded
    with_flange = [r for r in frames if any(None not in p for p in (r.get("flange_mm") or []))]
    assert with_flange
    assert [r["record"] for r in rows["world/flange/seen"]] == [r["seq"] for r in with_flange]
    assert [r["record"] for r in rows["world/robot/tcp"]] == [r["seq"] for r in frames]
    guides = rows["world/robot/guide"]
    assert [r["record"] for r in guides] == [r["seq"] for r in frames]
    for g in guides:
        (vx, vy, vz), = g["Arrows3D:vectors"]
        assert math.hypot(vx, vy, vz) == pytest.approx(GUIDE_ARROW_MM, rel=1e-5)
    plan = next(r for r in recs if r["event"] == "plan_accepted")
    assert _f32(rows["world/robot/plan/entry"][0]["Points3D:positions"]) == _f32([plan["entry_robot_mm"]])
    assert _f32(rows["world/robot/plan/target"][0]["Points3D:positions"]) == _f32([plan["target_robot_mm"]])
    commanded = [r["seq"] for r in recs if r["event"] == "command_sent" and r["command"] != "hold"]
    assert {r["command"] for r in recs if r["event"] == "command_sent"} == {"move_linear", "track", "hold"}
    assert [r["record"] for r in rows["world/robot/commanded"]] == commanded
    (robot,) = rows["world/robot"]
    assert robot["static"]
    assert robot["Transform3D:translation"] is not None


def test_truth_positions_match_the_log_exactly(sim_session: Path,
                                               replay: tuple[Path, dict[str, Any]]) -> None:
    """The simulator's truth (``truth_positions``, one per stereo pair) as points and a path,
    every record's values, record numbers and times."""
    from hil.controller.metrics import TRUTH_POSITIONS
    from hil.replay.scene import TRUTH_POSITIONS_EVENT

    assert TRUTH_POSITIONS_EVENT == TRUTH_POSITIONS
    recs = read_records(sim_session)
    t0 = recs[0]["t_ns"]
    truth = [r for r in recs if r["event"] == TRUTH_POSITIONS]
    frames = [r for r in recs if r["event"] == "frame_measured"]
    assert len(truth) == len(frames)  # one per new stereo pair
    assert [r["frame"] for r in truth] == list(range(1, len(frames) + 1))
    rows = _rows(replay[0])
    for field, entity in (("markers_optical_mm", "world/truth/skin"),
                          ("entry_optical_mm", "world/truth/entry"),
                          ("target_optical_mm", "world/truth/target")):
        want = [(r["seq"], r["t_ns"] - t0,
                 _f32(r[field] if field == "markers_optical_mm" else [r[field]])) for r in truth]
        got = [(g["record"], g["session_time"], _f32(g["Points3D:positions"])) for g in rows[entity]]
        assert got == want, entity
    assert all(len(r["markers_optical_mm"]) == 6 for r in truth)  # the phantom's six skin markers
    paths = rows["world/truth/path"]
    assert [(g["record"], _f32(g["LineStrips3D:strips"][0])) for g in paths] == \
        [(r["seq"], _f32([r["entry_optical_mm"], r["target_optical_mm"]])) for r in truth]


def test_transitions_are_annotated_in_order(sim_session: Path, replay: tuple[Path, dict[str, Any]]) -> None:
    recs = read_records(sim_session)
    t0 = recs[0]["t_ns"]
    want = [(r["seq"], r["t_ns"] - t0,
             f"{r['source']} -> {r['target']} ({r['transition']}: {r['reason']})")
            for r in recs if r["event"] == "transition_applied"]
    assert len(want) == 7  # idle -> register -> ... -> done
    got = [(r["record"], r["session_time"], r["TextLog:text"][0])
           for r in _rows(replay[0])["events/transitions"]]
    assert got == want
    (verification,) = _rows(replay[0])["session/verification"]
    assert verification["TextDocument:text"][0].startswith("verified")


def test_rerun_cli_verifies_the_file(replay: tuple[Path, dict[str, Any]]) -> None:
    proc = subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "verify", str(replay[0])],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "1 file verified without error" in proc.stderr + proc.stdout


def test_replay_of_the_default_run_is_fast(sim_session: Path, tmp_path: Path) -> None:
    import time

    from hil.replay import write_replay

    t = time.perf_counter()
    result = write_replay(sim_session, tmp_path / "timed.rrd")
    assert time.perf_counter() - t <= 5.0
    assert result.records == len(read_records(sim_session))


def test_analytics_are_turned_off_before_rerun_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.replay.rerun_env import analytics_config_path, disable_rerun_analytics

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "cfg"))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.setenv("FORCE_RERUN_ANALYTICS", "1")
    path = disable_rerun_analytics()
    assert path == analytics_config_path() == tmp_path / "cfg" / "rerun" / "analytics.json"
    doc = json.loads(path.read_text(encoding="utf-8"))
    assert doc["analytics_enabled"] is False
    assert doc["config_file_path"] == str(path)
    assert doc["data_dir_path"] == str(tmp_path / "data" / "rerun" / "analytics")
    import os

    assert "FORCE_RERUN_ANALYTICS" not in os.environ
    # an enabled file is switched off, its id kept
    path.write_text(json.dumps({**doc, "analytics_enabled": True, "analytics_id": "abc"}), encoding="utf-8")
    disable_rerun_analytics()
    doc2 = json.loads(path.read_text(encoding="utf-8"))
    assert doc2["analytics_enabled"] is False
    assert doc2["analytics_id"] == "abc"
    # Rerun's own CLI reads the same file and reports analytics off
    proc = subprocess.run([sys.executable, "-m", "rerun_cli", "analytics", "config"],
                          capture_output=True, text=True, timeout=60, check=False,
                          env={**os.environ})
    assert proc.returncode == 0, proc.stderr
    assert '"analytics_enabled": false' in proc.stdout.replace("\n", " ") or \
        "analytics_enabled: false" in proc.stdout, proc.stdout


def test_rerun_is_imported_with_the_footerless_file_warning_quieted(monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.replay.rerun_env import QUIET_FILE_SINK, RUST_LOG_ENV, quiet_file_sink_warning

    monkeypatch.delenv(RUST_LOG_ENV, raising=False)
    assert quiet_file_sink_warning() == f"warn,{QUIET_FILE_SINK}"
    assert quiet_file_sink_warning() == f"warn,{QUIET_FILE_SINK}"   # idempotent
    monkeypatch.setenv(RUST_LOG_ENV, "debug")   # a user's own filter is kept
    assert quiet_file_sink_warning() == f"debug,{QUIET_FILE_SINK}"
