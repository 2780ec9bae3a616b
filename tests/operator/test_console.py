"""hil console, headless (textual's pilot) over the real controller and the simulator:
a full procedure driven by key presses, a fault shown and recovered, an abort."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pyigtl
import pytest
from textual.widgets import DataTable, Static

from hil.console.app import ConfirmScreen, ConsoleApp
from hil.console.operator import ConsoleOperator
from hil.console.panels import gate_text, markers_title, registration_text
from hil.console.session import ConsoleSession
from hil.console.view import ConsoleView
from hil.controller.fsm import Event
from hil.errors import HilError
from hil.report import build_report
from hil.session.log import read_session_log, verify_session_log
from tests.operator.console_helpers import (
    SIM_PLAN,
    SessionOpener,
    quit_app,
    wait_controller,
    wait_message,
    wait_prompt,
    wait_view,
    write_setup,
)

SIZE = (170, 50)


def _events(log: Path) -> list[dict[str, object]]:
    return list(read_session_log(log))


def _transitions(log: Path) -> list[str]:
    return [str(r["transition"]) for r in _events(log) if r["event"] == "transition_applied"]


def _text(app: ConsoleApp, wid: str) -> str:
    return str(app.query_one(wid, Static).render())


def test_marker_table_title_counts_per_camera() -> None:
    assert markers_title(None) == "Markers (optical frame)"
    assert markers_title((10, 9, 8)) == "Markers (optical frame) — located: left 10, right 9, 3-D 8"
    assert markers_title((None, None, 3)) == "Markers (optical frame) — located: left —, right —, 3-D 3"


def test_operator_queue_takes_only_operator_commands() -> None:
    op = ConsoleOperator()
    with pytest.raises(HilError, match="gate_opened is not an operator command"):
        op.post(Event.GATE_OPENED)
    with pytest.raises(HilError, match="registered is not an operator command"):
        op.post(Event.REGISTERED)
    assert op.post(Event.START_REQUESTED, origin="key s") is None
    assert op.post(Event.ABORT_REQUESTED) is None
    assert op.pending_commands() == 2
    view = None
    first, second = op.poll(view), op.poll(view)  # type: ignore[arg-type]
    assert first is not None
    assert first.event is Event.START_REQUESTED
    assert (first.seq, first.origin) == (1, "key s")
    assert second is not None
    assert second.event is Event.ABORT_REQUESTED
    assert second.seq == 2
    assert op.poll(view) is None  # type: ignore[arg-type]
    assert not op.finished(view)  # type: ignore[arg-type]
    op.request_quit()
    assert op.finished(view)  # type: ignore[arg-type]


def test_full_procedure_by_key_presses(tmp_path: Path, open_session: SessionOpener) -> None:
    asyncio.run(_full_procedure_by_key_presses(tmp_path, open_session))


async def _full_procedure_by_key_presses(tmp_path: Path, open_session: SessionOpener) -> None:
    setup = write_setup(tmp_path)
    session = open_session(setup, plan=SIM_PLAN, session_dir=tmp_path / "sessions", fast=False,
                           igtl_port=0)
    assert session.igtl is not None
    host, port = session.igtl.address
    assert host == "127.0.0.1"
    client = pyigtl.OpenIGTLinkClient(host=host, port=port)
    try:
        app = ConsoleApp(session)
        prompts: list[str] = []
        async with app.run_test(size=SIZE) as pilot:
            await wait_view(pilot, app, lambda v: session.igtl.clients == 1, "OpenIGTLink client connected")
            v = await wait_view(pilot, app, lambda v: v.state == "idle", "idle")
            assert "press s to start" in _text(app, "#workflow")
            await pilot.press("s")
            for expected in ("plan_to_approach", "lock_to_done"):  # the sim config's confirmations
                await wait_prompt(pilot, app, expected)
                v = session.runner.latest()
                assert v is not None
                assert v.pending == expected
                assert isinstance(app.screen, ConfirmScreen)
                prompts.append(expected)
                if expected == "lock_to_done":
                    # everything on screen while locked
                    assert "lock" in _text(app, "#workflow")
                    assert f"{session.ctl.patient_reg.fre_rms_mm:.3f} mm" in _text(app, "#registration")  # type: ignore[union-attr]
                    table = app.query_one("#markers", DataTable)
                    assert table.row_count == 6 + 4  # skin markers of the plan + flange markers
                    assert re.fullmatch(r"Markers \(optical frame\) — located: left \d+, right \d+, 3-D \d+",
                                        str(table.border_title))
                    assert "OPEN" in _text(app, "#gate")
                    app.save_screenshot(filename="console_lock.svg", path=str(tmp_path))
                    _check_igtl_stream(client, session)
                await pilot.press("c")
                await wait_view(pilot, app, lambda v, e=expected: v.pending != e, f"{expected} confirmed")
            v = await wait_view(pilot, app, lambda v: v.state == "done", "done")
            assert v.faults == ()
            assert v.fre_mm is not None
            assert len(v.breathing_mm) > 10
            # every seen skin marker shows its deviation from the registered state (the gate's
            # per-marker check), and it is what the snapshot holds
            skin = [m for m in v.markers if m.kind == "skin" and m.visible]
            assert skin
            assert all(m.deviation_mm is not None and 0.0 <= m.deviation_mm < 5.0 for m in skin)
            summary = await quit_app(pilot, app)
    finally:
        client.stop()
    assert prompts == ["plan_to_approach", "lock_to_done"]
    assert summary["final_state"] == "done"
    log = Path(str(summary["session_log"]))
    chain = verify_session_log(log)
    assert chain.ok
    assert chain.closed
    header = _events(log)[0]
    assert (header["event"], header["origin"]) == ("session_started", "console")
    assert len(header["config_sha256"]) == 64
    assert isinstance(header["perception_process"], bool)   # where markers were located, and why
    assert (header["perception_in_supervisor_because"] is None) == header["perception_process"]
    assert _transitions(log) == ["start", "register_to_plan", "plan_to_approach", "approach_to_gate",
                                 "gate_to_compensate", "compensate_to_lock", "lock_to_done"]
    cmds = [r["input"] for r in _events(log) if r["event"] == "operator_command"]
    assert cmds == ["start_requested", "confirm_requested", "confirm_requested"]
    results = [(r["input"], r["outcome"]) for r in _events(log) if r["event"] == "operator_command_result"]
    assert results == [("start_requested", "executed"), ("confirm_requested", "executed"),
                       ("confirm_requested", "executed")]
    assert (tmp_path / "console_lock.svg").stat().st_size > 10_000
    # the recorded session makes a full report
    rep = build_report(log, tmp_path / "report")
    nums = {n.key: n.value for n in rep.numbers}
    assert nums["fre_mm"] == pytest.approx(session.ctl.patient_reg.fre_rms_mm)  # type: ignore[union-attr]
    assert nums["final_state"] == "done"
    # residuals: frame_measured carries live_mm and registration_done residuals_mm
    # no target model in this config: its plot says so instead of drawing
    assert {p.key: p.has_data for p in rep.plots} == {"states": True, "breathing": True, "errors": True,
                                                      "residuals": True, "body": True, "speed": True,
                                                      "target": False}


def test_fault_shown_and_recovered(tmp_path: Path, open_session: SessionOpener) -> None:
    asyncio.run(_fault_shown_and_recovered(tmp_path, open_session))


def _statuses_until(client: pyigtl.OpenIGTLinkClient, prefix: str, timeout_s: float) -> list[str]:
    """The Status strings received until one starts with ``prefix`` or ``timeout_s`` passes."""
    seen: list[str] = []
    deadline = time.monotonic() + timeout_s
    while not (seen and seen[-1].startswith(prefix)):
        left_s = deadline - time.monotonic()
        if left_s <= 0:
            break
        msg = client.wait_for_message("Status", timeout=left_s)
        if msg is not None:
            seen.append(str(msg.string))
    return seen


def _check_igtl_stream(client: pyigtl.OpenIGTLinkClient, session: ConsoleSession) -> None:
    """While locked: the streamed matrices are the controller's own (registration exactly, in
    float32; the guide where the plan puts it: on the path, the stand-off above the entry)."""
    ctl = session.ctl
    assert ctl.patient_reg is not None
    msg = client.wait_for_message("ImageToOptical", timeout=10.0)
    assert msg is not None
    np.testing.assert_array_equal(np.asarray(msg.matrix, dtype=np.float32)[:3],
                                  ctl.patient_reg.T_optical_from_image.as_matrix().astype(np.float32)[:3])
    msg = client.wait_for_message("GuideToImage", timeout=10.0)
    assert msg is not None
    M = np.asarray(msg.matrix, dtype=np.float64)
    entry, target = ctl.plan.entry_mm.reshape(3), ctl.plan.target_mm.reshape(3)
    u = (target - entry) / np.linalg.norm(target - entry)
    assert ctl.guide_plan is not None
    ideal = entry - ctl.guide_plan.standoff_mm * u
    assert float(np.linalg.norm(M[:3, 3] - ideal)) < 1.0  # locked: lock tolerance + registration
    assert float(np.degrees(np.arccos(np.clip(M[:3, 2] @ u, -1, 1)))) < 1.0
    # the status streams at its own rate: the one naming the confirmation on screen comes within
    # a status period of the prompt (earlier ones, already received, say LOCK without it)
    statuses = _statuses_until(client, "state=lock pending=lock_to_done", timeout_s=10.0)
    assert statuses[-1].startswith("state=lock pending=lock_to_done"), statuses
    assert all(s.startswith("state=lock") for s in statuses), statuses
    pts = client.wait_for_message("Plan", timeout=10.0)
    assert pts is not None
    np.testing.assert_allclose(np.asarray(pts.positions, dtype=float), [entry, target], atol=1e-4)


async def _fault_shown_and_recovered(tmp_path: Path, open_session: SessionOpener) -> None:
    # a protective stop of the arm after the plan was confirmed (approach or gate)
    setup = write_setup(tmp_path, '\n[[faults]]\nkind = "protective_stop"\nstart_s = 5.0\nduration_s = 0.2\n')
    session = open_session(setup, plan=SIM_PLAN, session_dir=tmp_path / "sessions", fast=False)
    app = ConsoleApp(session)
    async with app.run_test(size=SIZE) as pilot:
        await wait_view(pilot, app, lambda v: v.state == "idle", "idle")
        await pilot.press("s")
        await wait_prompt(pilot, app, "plan_to_approach")
        await pilot.press("c")
        v = await wait_view(pilot, app, lambda v: v.state == "fault", "fault")
        await pilot.pause()
        banner = _text(app, "#banner")
        assert banner.startswith("FAULT: ")
        assert "protective_stop" in banner
        assert "way out: fault: r recover" in banner
        assert app.query_one("#banner", Static).has_class("shown")
        assert "protective_stop" in v.faults[0]
        # The operator presses r at once. While the injected stop holds (to t = 5.2 s) recover()
        # is refused and the arm faults again - visibly; once its window has passed, r recovers.
        decided = v.operator_commands_decided
        await pilot.press("r")
        v = await wait_view(pilot, app, lambda v: v.operator_commands_decided > decided, "r decided")
        if v.state == "fault":
            await wait_view(pilot, app, lambda v: v.t_s > 5.2, "the stop's window over")
            await pilot.press("r")
        v = await wait_view(pilot, app, lambda v: v.state in ("gate", "compensate", "lock"), "recovered")
        assert not app.query_one("#banner", Static).has_class("shown")
        summary = await quit_app(pilot, app)
    # a refresh tick landing while the app shuts down (its widgets removed before its timers
    # stop, as when a test fails inside the app) does nothing instead of raising NoMatches
    app.refresh_view()
    log = Path(str(summary["session_log"]))
    tr = _transitions(log)
    assert tr[:3] == ["start", "register_to_plan", "plan_to_approach"]
    i_fault = tr.index("fault")
    assert tr[i_fault + 1] in ("recover", "fault")  # a refused recover() faults again, then recovers
    assert "recover" in tr[i_fault + 1:]
    assert "approach_to_gate" in tr[i_fault + 2:]
    # quitting while the procedure was under way aborted it: robot stopped, safe stop
    assert summary["final_state"] == "safe_stop"
    assert tr[-1] == "abort"
    assert verify_session_log(log).ok


def test_abort_and_rejected_command(tmp_path: Path, open_session: SessionOpener) -> None:
    asyncio.run(_abort_and_rejected_command(tmp_path, open_session))


async def _abort_and_rejected_command(tmp_path: Path, open_session: SessionOpener) -> None:
    # a slow approach (~14 s of motion, paced to the wall clock): the test samples the controller's
    # snapshots from the UI loop, which on a loaded machine can miss the default ~1.6 s approach
    setup = write_setup(tmp_path, "\n[procedure.approach]\nspeed_mm_s = 5.0\n")
    session = open_session(setup, plan=SIM_PLAN, session_dir=tmp_path / "sessions", fast=False)
    app = ConsoleApp(session)
    async with app.run_test(size=SIZE) as pilot:
        await wait_view(pilot, app, lambda v: v.state == "idle", "idle")
        await pilot.press("p")  # nothing to pause: rejected by the state machine, and said so
        await wait_message(pilot, app, lambda m: m.startswith("pause: rejected"), "pause rejected")
        await pilot.press("s")
        await wait_prompt(pilot, app, "plan_to_approach")
        await pilot.press("c")
        await wait_view(pilot, app, lambda v: v.state == "approach" and (v.robot_speed_mm_s or 0) > 1.0,
                        "robot moving")
        await pilot.press("a")
        await wait_view(pilot, app, lambda v: v.state == "safe_stop", "safe stop")
        await pilot.pause()
        assert _text(app, "#banner").startswith("SAFE_STOP")
        await wait_view(pilot, app, lambda v: v.robot_speed_mm_s == 0.0, "robot at rest")
        summary = await quit_app(pilot, app)
    assert summary["final_state"] == "safe_stop"
    log = Path(str(summary["session_log"]))
    ev = _events(log)
    rejected = [r for r in ev if r["event"] == "transition_rejected"]
    assert rejected[0]["input"] == "pause_requested"
    assert rejected[0]["source"] == "idle"
    assert _transitions(log) == ["start", "register_to_plan", "plan_to_approach", "abort"]
    i_abort = next(i for i, r in enumerate(ev)
                   if r["event"] == "transition_applied" and r["transition"] == "abort")
    assert any(r["event"] == "stop_sent" for r in ev[i_abort:])
    assert json.dumps(summary)  # the CLI prints it as JSON


def test_cli_bad_config_and_plan_are_one_line_errors(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from hil.cli import main

    assert main(["console", str(tmp_path / "missing.toml"), "--session-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith(f"hil console: error: {tmp_path / 'missing.toml'}: ")
    setup = write_setup(tmp_path)
    assert main(["console", str(setup), "--plan", str(tmp_path / "nope.json"),
                 "--session-dir", str(tmp_path)]) == 2
    assert "nope.json: cannot read plan" in capsys.readouterr().err


def test_ui_stays_responsive_while_the_loop_is_blocked(tmp_path: Path, open_session: SessionOpener) -> None:
    asyncio.run(_ui_stays_responsive(tmp_path, open_session))


async def _ui_stays_responsive(tmp_path: Path, open_session: SessionOpener) -> None:
    """A controller tick stuck in a device call (here: held on an event) must not freeze the UI:
    keys are still taken and queued, and applied once the loop moves again."""
    session = open_session(write_setup(tmp_path), plan=SIM_PLAN, session_dir=tmp_path / "s")
    hold, held = threading.Event(), threading.Event()
    release = threading.Event()
    real_tick = session.ctl.tick

    def tick() -> None:
        if hold.is_set() and not release.is_set():
            held.set()
            release.wait(30.0)
        real_tick()

    session.ctl.tick = tick  # type: ignore[method-assign]
    app = ConsoleApp(session)
    try:
        async with app.run_test(size=SIZE) as pilot:
            await wait_view(pilot, app, lambda v: v.state == "idle", "idle")
            hold.set()
            await wait_view(pilot, app, lambda v: held.is_set(), "loop held inside a tick")
            await pilot.press("s")  # returns although the loop is stuck
            await pilot.press("p")  # pressed while the start is not yet applied
            assert session.operator.pending_commands() == 2
            await pilot.pause(0.2)  # two UI refreshes
            assert "2 command(s) waiting for the controller" in _text(app, "#messages")
            v = session.runner.latest()
            assert v is not None
            assert v.state == "idle"  # nothing applied while the loop is stuck
            release.set()
            await wait_view(pilot, app, lambda v: v.operator_commands_decided == 2, "both decided")
            # in order: the start, then the pause judged in the state the start led to
            await wait_message(pilot, app, lambda m: m.startswith("pause:"), "pause verdict")
            assert app.messages[:2] == [
                "start: executed — start: idle -> register",
                "pause: rejected — nothing is moving or waiting to move here"]
            summary = await quit_app(pilot, app)
    finally:
        release.set()
    assert summary["final_state"] == "safe_stop"


def test_a_full_queue_and_a_closing_console_refuse_commands_and_say_why() -> None:
    from hil.console.operator import MAX_QUEUED

    op = ConsoleOperator()
    for _ in range(MAX_QUEUED):
        assert op.post(Event.PAUSE_REQUESTED, origin="key p") is None
    refused = op.post(Event.ABORT_REQUESTED, origin="key a")
    assert refused is not None
    assert refused.outcome == "refused"
    assert refused.input == "abort_requested"
    assert refused.reason == f"{MAX_QUEUED} commands already wait for the controller (it is not ticking)"
    assert op.pending_commands() == MAX_QUEUED  # the newest is refused, no queued one is dropped
    op.request_quit()
    closing = op.post(Event.START_REQUESTED, origin="key s")
    assert closing is not None
    assert closing.reason == "the console is closing (the procedure is being aborted)"
    assert [r.seq for r in op.drain_refused()] == [MAX_QUEUED + 1, MAX_QUEUED + 2]
    assert op.drain_refused() == []  # handed over once, for the session log
    assert [r.message() for r in op.take_results()] == [
        f"abort: refused — {refused.reason}", f"start: refused — {closing.reason}"]


def test_early_repeated_and_declined_confirmations(tmp_path: Path, open_session: SessionOpener) -> None:
    asyncio.run(_early_repeated_and_declined_confirmations(tmp_path, open_session))


async def _early_repeated_and_declined_confirmations(tmp_path: Path, open_session: SessionOpener) -> None:
    """c pressed before the prompt is on screen is refused and said (it never confirms a motion
    the operator did not see); n on the prompt ("not now") declines and keeps the confirmation
    pending; c then confirms; c pressed again confirms nothing more. Each verdict is on screen
    and in the log."""
    session = open_session(write_setup(tmp_path), plan=SIM_PLAN, session_dir=tmp_path / "s")
    app = ConsoleApp(session)
    async with app.run_test(size=SIZE) as pilot:
        await wait_view(pilot, app, lambda v: v.state == "idle", "idle")
        app.refresh_timer.pause()  # the screen keeps showing IDLE: no prompt can open
        await pilot.press("s")
        await wait_controller(pilot, app, lambda v: v.pending == "plan_to_approach", "plan pending")
        assert not isinstance(app.screen, ConfirmScreen)
        await pilot.press("c")  # early: the operator has not seen the prompt
        await wait_controller(pilot, app, lambda v: v.operator_commands_decided == 2, "early c decided")
        app.refresh_timer.resume()
        early = await wait_message(pilot, app, lambda m: m.startswith("confirm: rejected"), "early c")
        assert "no prompt was shown when this was pressed" in early
        assert early in _text(app, "#messages")
        await wait_prompt(pilot, app, "plan_to_approach")  # still pending: nothing was confirmed
        await pilot.press("n")
        await wait_message(pilot, app, lambda m: m.startswith("confirm: declined"), "declined")
        v = await wait_view(pilot, app, lambda v: v.operator_commands_decided == 3, "n decided")
        assert v.state == "plan"
        assert v.pending == "plan_to_approach"
        assert not isinstance(app.screen, ConfirmScreen)  # the prompt was answered
        await pilot.press("c")  # the confirmation shown on the workflow line
        await pilot.press("c")  # repeated
        v = await wait_view(pilot, app, lambda v: v.operator_commands_decided == 5, "both c decided")
        assert v.state not in ("idle", "register", "plan", "fault")
        # the second c named plan_to_approach if the screen had not refreshed yet, else nothing
        again = await wait_message(pilot, app, lambda m: m.startswith("confirm: rejected — nothing"),
                                   "repeated c")
        assert again in ("confirm: rejected — nothing awaits confirmation",
                         "confirm: rejected — nothing awaits confirmation "
                         "(plan_to_approach was already decided)")
        summary = await quit_app(pilot, app)
    log = Path(str(summary["session_log"]))
    results = [(r["origin"], r["outcome"]) for r in _events(log) if r["event"] == "operator_command_result"]
    assert results[:5] == [("key s", "executed"), ("key c", "rejected"), ("prompt not now", "declined"),
                           ("key c", "executed"), ("key c", "rejected")]
    assert _transitions(log)[:3] == ["start", "register_to_plan", "plan_to_approach"]


def _gate_view(target_shift_mm: float | None = None, target_turn_deg: float | None = None,
               target_fallback: str | None = None) -> ConsoleView:
    return ConsoleView(
        t_s=0.0, state="compensate", pending=None, pending_reason="", last_reason="", hint="",
        markers=(), gate_deviation_mm=0.5, gate_tolerance_mm=1.5, gate_dwell_s=0.5, gate_open=True,
        breathing_mm=(), robot_connected=True, robot_mode="running", robot_safety="normal",
        robot_speed_mm_s=None, robot_tcp_mm=None, guide_error_mm=None, fre_mm=None, tre_expected_mm=None,
        robot_fre_mm=None, comp_error_mm=None, faults=(), timeline=(), plan_source="p.json",
        plan_fiducials=6, plan_entry_mm=(0.0, 0.0, 0.0), plan_target_mm=(0.0, 0.0, -75.0), frames=0,
        commands_sent=0, commands_refused=0, operator_commands_decided=0, session_log="", igtl="",
        change_estimator="rigid", change_fre_mm=0.4, target_shift_mm=target_shift_mm,
        target_turn_deg=target_turn_deg, target_fallback=target_fallback)


def test_the_gate_panel_says_what_the_target_model_does() -> None:
    assert "target model" not in str(gate_text(_gate_view()))              # no model: nothing said
    steered = str(gate_text(_gate_view(target_shift_mm=6.25, target_turn_deg=3.5, target_fallback="")))
    assert "\ntarget model: target 6.250 mm from plan, path turned 3.50 deg" in steered
    kept = str(gate_text(_gate_view(target_shift_mm=0.0, target_turn_deg=0.0, target_fallback="why not")))
    assert "\ntarget model: rigid direction kept (why not)" in kept
    assert "held at its bounds" not in steered
    bound = "the model's turn 12.0 deg held at the bound 10.0 deg"
    view = _gate_view(target_shift_mm=9.0, target_turn_deg=10.0, target_fallback="")
    held = str(gate_text(dataclasses.replace(view, target_limited=bound)))
    assert f"path turned 10.00 deg\n  held at its bounds: {bound}" in held


def test_the_registration_panel_says_where_the_breathing_moved_the_path() -> None:
    view = _gate_view()
    assert "breathing" not in str(registration_text(view))           # no 4D CT model: nothing said
    moved = dataclasses.replace(view, breathing_entry_shift_mm=0.6, breathing_target_shift_mm=1.35,
                                breathing_kept_rigid_because="")
    assert str(registration_text(moved)).endswith("\nbreathing      entry moved 0.600 mm, target 1.350 mm")
    kept = dataclasses.replace(moved, breathing_kept_rigid_because="3 markers seen")
    assert str(registration_text(kept)).endswith("\nbreathing      Horn's fit kept: 3 markers seen")
