"""``hil soak --viewer``: the live viewer plugin on the soak's hooks, the truth streamed, the
stream's cost reported, a bad target refused before anything starts, and the stream's thread
closed on every path (a full soak with the viewer is measured in docs/benchmarks.md)."""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from hil.cli import main
from hil.errors import InputFileError
from hil.soak.viewer import (
    check_viewer_target,
    close_soak_viewer,
    follow_truth,
    open_devices_and_viewer,
    open_soak_viewer,
)


def _viewer_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "hil-viewer"]


def _snap(t_ns: int) -> Any:
    return SimpleNamespace(t_ns=t_ns, T_robot_from_optical=None, live_mm=None, flange_mm=None, robot_now=None,
                           robot=None, gate_deviation_mm=None, guide_error_mm=0.5, truth_error_mm=None)


def test_a_viewer_in_a_missing_directory_is_refused_before_the_soak_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "no" / "soak.rrd"
    with pytest.raises(InputFileError, match="directory does not exist"):
        check_viewer_target(str(target))
    check_viewer_target(None)
    check_viewer_target("rerun+http://127.0.0.1:9876/proxy")  # an address is not a file
    code = main(["soak", "--minutes", "0.1", "--rate", "500", "--probe-host", "0",
                 "--session-dir", str(tmp_path), "--viewer", str(target)])
    assert code == 2
    assert capsys.readouterr().err.splitlines() == [
        f"hil soak: error: {target}: --viewer: the recording's directory does not exist"]
    assert not list(tmp_path.glob("soak_*.jsonl"))  # nothing started


def test_the_stream_is_on_the_hooks_follows_the_truth_and_reports_its_cost(tmp_path: Path) -> None:
    live, hooks = open_soak_viewer(str(tmp_path / "soak.rrd"))
    try:
        impls = hooks.implementations("hil_on_tick")
        assert [name for name, _ in impls] == ["rerun_viewer"]  # no installed plugin beside it
        meter = SimpleNamespace(last_positions=None)
        follow_truth(live, SimpleNamespace(truth_meter=meter))  # type: ignore[arg-type]
        for i in range(10):
            meter.last_positions = {"truth_t_ns": 1000 * (i // 2), "entry_optical_mm": [0.0, 0.0, float(i)]}
            for _, fn in impls:
                fn(snapshot=_snap(1000 * i))
    finally:
        figures = close_soak_viewer(live)
    assert {k: figures[k] for k in ("offered", "written", "dropped", "write_errors", "lost_on_close",
                                    "truth_written", "hook_calls")} == {
        "offered": 10, "written": 10, "dropped": 0, "write_errors": 0, "lost_on_close": 0,
        "truth_written": 5, "hook_calls": 10}
    hook = figures["hook_ms"]
    assert set(hook) == {"p50", "p99", "max"}
    assert 0 < hook["p50"] <= hook["p99"] <= hook["max"]
    assert (tmp_path / "soak.rrd").stat().st_size > 0
    assert close_soak_viewer(None) == {}
    assert not _viewer_threads()


class _Unopenable:
    def open_all(self) -> None:
        raise OSError("the arm is not there")


def test_the_stream_is_closed_when_the_devices_fail_to_open(tmp_path: Path) -> None:
    with pytest.raises(OSError, match="not there"):
        open_devices_and_viewer(_Unopenable(), str(tmp_path / "soak.rrd"))  # type: ignore[arg-type]
    assert not _viewer_threads()
    assert open_devices_and_viewer(SimpleNamespace(open_all=lambda: None), None) == (None, None)  # type: ignore[arg-type]
