"""The console's confirmation keys, pressed as an operator reads them off the screen: the
workflow line, the footer on top and the dialog's buttons name one vocabulary, and pressing what
they name acts; any other key pressed on the dialog is answered on the dialog (issue 45 item 6).

Every key pressed here is read from the screen first (never a literal from the code)."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

from textual.pilot import Pilot
from textual.widgets import Button, Footer, Label, Static

from hil.console.app import ConfirmScreen, ConsoleApp
from hil.session.log import read_session_log
from tests.operator.console_helpers import (
    DEADLINE_S,
    SIM_PLAN,
    SessionOpener,
    quit_app,
    wait_message,
    wait_prompt,
    wait_view,
    write_setup,
)

SIZE = (170, 50)
_FOOTER_ITEM = re.compile(r"^\s*(\S+)\s+(\S.*?)\s*$")


def _workflow(app: ConsoleApp) -> str:
    return str(app.query_one("#workflow", Static).render())


def _key_named_on_workflow(app: ConsoleApp, word: str) -> str:
    """The key the workflow line tells the operator to press for ``word`` ("press c (confirm)")."""
    text = _workflow(app)
    m = re.search(rf"(?:press |, | or )(\S+) \({word}\)", text)
    assert m is not None, f"the workflow line names no key for {word!r}: {text!r}"
    return m.group(1)


def _visible_footer(app: ConsoleApp) -> dict[str, str]:
    """The footer the operator sees (the topmost screen's that has one: a dialog's own footer
    covers the one below): description -> key, as rendered."""
    for screen in reversed(app.screen_stack):
        footers = list(screen.query(Footer))
        if footers:
            items: dict[str, str] = {}
            for child in footers[0].children:
                m = _FOOTER_ITEM.match(str(child.render()))
                if m is not None:
                    items[m.group(2)] = m.group(1)
            return items
    raise AssertionError("no footer on screen")


async def _footer_naming(pilot: Pilot[object], app: ConsoleApp, description: str) -> str:
    """The key the visible footer shows for ``description``, once the footer is drawn (bounded)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + DEADLINE_S
    while description not in (shown := _visible_footer(app)):
        if loop.time() > end:
            raise AssertionError(f"the footer shows no {description!r}: {shown}")
        await pilot.pause(0.05)
    return shown[description]


def _dialog_buttons(app: ConsoleApp) -> dict[str, str]:
    """The open dialog's buttons: label word(s) -> the key in the label ("Confirm (c)")."""
    assert isinstance(app.screen, ConfirmScreen)
    out: dict[str, str] = {}
    for b in app.screen.query(Button):
        m = re.fullmatch(r"(.+) \((\S+)\)", str(b.label))
        assert m is not None, f"a dialog button names no key: {b.label}"
        out[m.group(1)] = m.group(2)
    return out


async def _one_key(pilot: Pilot[object], app: ConsoleApp, word: str, footer: str) -> str:
    """The key for ``word``: named alike by the workflow line, the visible footer and (with a
    dialog open) the dialog's button."""
    key = _key_named_on_workflow(app, word)
    assert await _footer_naming(pilot, app, footer) == key, (word, _visible_footer(app))
    if isinstance(app.screen, ConfirmScreen):
        assert _dialog_buttons(app)[footer] == key, (word, _dialog_buttons(app))
    return key


def test_pressing_what_the_screen_says_confirms(tmp_path: Path, open_session: SessionOpener) -> None:
    asyncio.run(_pressing_what_the_screen_says_confirms(tmp_path, open_session))


async def _pressing_what_the_screen_says_confirms(tmp_path: Path, open_session: SessionOpener) -> None:
    """At each prompt: "not now" read off the screen closes the prompt and keeps the
    confirmation pending; "confirm" read off the screen (dialog closed, then open) confirms."""
    session = open_session(write_setup(tmp_path), plan=SIM_PLAN, session_dir=tmp_path / "s")
    app = ConsoleApp(session)
    async with app.run_test(size=SIZE) as pilot:
        await wait_view(pilot, app, lambda v: v.state == "idle", "idle")
        await pilot.press("s")
        await wait_prompt(pilot, app, "plan_to_approach")
        await pilot.press(await _one_key(pilot, app, "not now", "Not now"))
        await wait_message(pilot, app, lambda m: m.startswith("confirm: declined"), "not now")
        v = await wait_view(pilot, app, lambda v: v.operator_commands_decided == 2, "not now decided")
        assert (v.state, v.pending) == ("plan", "plan_to_approach")
        assert not isinstance(app.screen, ConfirmScreen)
        # the dialog is closed: the workflow line and the app's footer still name the same key
        await pilot.press(await _one_key(pilot, app, "confirm", "Confirm"))
        v = await wait_view(pilot, app, lambda v: v.pending != "plan_to_approach", "plan confirmed")
        assert v.state not in ("idle", "register", "plan", "fault", "safe_stop")
        await wait_prompt(pilot, app, "lock_to_done")
        await pilot.press(await _one_key(pilot, app, "confirm", "Confirm"))
        v = await wait_view(pilot, app, lambda v: v.state == "done", "done")
        assert v.faults == ()
        summary = await quit_app(pilot, app)
    log = Path(str(summary["session_log"]))
    results = [(r["origin"], r["input"], r["outcome"]) for r in read_session_log(log)
               if r["event"] == "operator_command_result"]
    assert results == [("key s", "start_requested", "executed"),
                       ("prompt not now", "confirm_requested", "declined"),
                       ("key c", "confirm_requested", "executed"),
                       ("prompt confirm", "confirm_requested", "executed")]


def test_every_key_on_the_dialog_acts_or_says_why(tmp_path: Path, open_session: SessionOpener) -> None:
    asyncio.run(_every_key_on_the_dialog_acts_or_says_why(tmp_path, open_session))


async def _every_key_on_the_dialog_acts_or_says_why(tmp_path: Path, open_session: SessionOpener) -> None:
    """y (the old dialog's key) and p (a command the dialog does not take) are answered on the
    dialog, which stays open, and post nothing; "abort" read off the screen aborts."""
    session = open_session(write_setup(tmp_path), plan=SIM_PLAN, session_dir=tmp_path / "s")
    app = ConsoleApp(session)
    async with app.run_test(size=SIZE) as pilot:
        await wait_view(pilot, app, lambda v: v.state == "idle", "idle")
        await pilot.press("s")
        await wait_prompt(pilot, app, "plan_to_approach")
        confirm = await _one_key(pilot, app, "confirm", "Confirm")
        not_now = await _one_key(pilot, app, "not now", "Not now")
        abort = await _one_key(pilot, app, "abort", "Abort")
        said: list[str] = []
        for key in ("y", "p"):
            await pilot.press(key)
            assert isinstance(app.screen, ConfirmScreen)  # still open
            said.append(str(app.screen.query_one("#confirm-said", Label).render()))
        keys = f"press {confirm} (confirm), {not_now} (not now) or {abort} (abort)"
        assert said == [f"y is not a key of this dialog: {keys}",
                        f"p (Pause) is not taken while a confirmation is open: {keys}"]
        assert session.operator.pending_commands() == 0
        v = session.runner.latest()
        assert v is not None
        assert (v.operator_commands_decided, v.pending) == (1, "plan_to_approach")
        await pilot.press(abort)
        v = await wait_view(pilot, app, lambda v: v.state == "safe_stop", "aborted")
        assert v.pending is None
        assert not isinstance(app.screen, ConfirmScreen)
        summary = await quit_app(pilot, app)
    log = Path(str(summary["session_log"]))
    results = [(r["origin"], r["input"], r["outcome"]) for r in read_session_log(log)
               if r["event"] == "operator_command_result"]
    assert results == [("key s", "start_requested", "executed"),
                       ("prompt abort", "abort_requested", "executed")]
