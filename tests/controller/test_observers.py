"""Controller observers (display, OpenIGTLink): called after every tick, never able to stop control."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from hil.config import load_setup
from hil.controller.controller import Controller
from hil.controller.plan_file import load_plan
from hil.controller.snapshot import ControllerSnapshot
from hil.session import read_session_log

CONFIG = Path("configs/sim.toml")
PLAN = load_plan("configs/plans/sim_plan.json")


def _run(tmp_path: Path, max_s: float, **kw: Any) -> Any:
    from hil.cli.cmd_run import run_procedure

    return run_procedure(CONFIG, kw.pop("setup", load_setup(CONFIG)), PLAN, auto=True, session_dir=tmp_path,
                         max_duration_s=max_s, **kw)


def test_observers_see_every_tick_and_their_failures_are_logged_once(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import hil.controller.assembly as assembly

    seen: list[tuple[str, int]] = []

    def watcher(snap: ControllerSnapshot) -> None:
        seen.append((snap.state, snap.frames))

    def broken(snap: ControllerSnapshot) -> None:
        raise RuntimeError("display gone")

    real = assembly.Controller

    def with_observers(**kw: Any) -> Controller:
        kw["observers"] = (broken, watcher)
        return real(**kw)

    monkeypatch.setattr(assembly, "Controller", with_observers)
    s = _run(tmp_path, 3.0)
    assert s.states[:2] == ["idle", "register"]
    # one call per tick (every tick grabbed a frame here), and one after the time-limit abort
    assert [f for _, f in seen] == [*range(1, s.frames + 1), s.frames]
    assert seen[-1][0] == "safe_stop"
    assert seen[0][0] == "register"
    failed = [r for r in read_session_log(s.session_log) if r["event"] == "observer_failed"]
    assert [(r["observer"], r["error"]) for r in failed] == [("broken", "RuntimeError: display gone")]
    assert s.faults == []


def test_hil_run_streams_to_openigtlink_when_enabled(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.igtl.server import IgtlServer
    from hil.igtl.snapshot import IgtlSnapshot

    published: list[IgtlSnapshot] = []
    closed: list[tuple[str, int]] = []
    real_close = IgtlServer.close

    def publish(self: IgtlServer, snap: IgtlSnapshot, now_ns: int | None = None, *,
                force: bool = False) -> int:
        published.append(snap)
        return 0

    def close(self: IgtlServer) -> None:
        closed.append(self.address)
        real_close(self)

    monkeypatch.setattr(IgtlServer, "publish", publish)
    monkeypatch.setattr(IgtlServer, "close", close)
    base = load_setup(CONFIG)
    setup = base.model_copy(update={"igtl": base.igtl.model_copy(update={"enabled": True, "port": 0})})
    s = _run(tmp_path, 3.0, setup=setup)
    assert len(published) == s.frames + 1  # every tick, and the time-limit abort after the last
    assert published[-1].status.startswith(f"state={s.final_state}")
    assert "ImageToOptical" in published[-1].transforms  # registered within 3 s
    assert len(closed) == 1
    assert closed[0][0] == "127.0.0.1"
    assert closed[0][1] > 0  # the bound port (0 asked for a free one)


def test_hil_run_does_not_start_openigtlink_by_default(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.igtl.server import IgtlServer

    def refuse(self: IgtlServer) -> None:
        raise AssertionError("started")

    monkeypatch.setattr(IgtlServer, "start", refuse)
    assert not load_setup(CONFIG).igtl.enabled
    assert _run(tmp_path, 0.5).frames > 0
