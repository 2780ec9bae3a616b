"""Helpers for the console's headless tests: a setup file with chosen faults, waiting on the
(real, threaded) controller with a deadline."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from textual.pilot import Pilot

from hil.console.app import ConsoleApp
from hil.console.session import ConsoleSession
from hil.console.view import ConsoleView

REPO = Path(__file__).resolve().parents[2]
SIM_TOML = REPO / "configs" / "sim.toml"
SIM_PLAN = REPO / "configs" / "plans" / "sim_plan.json"
DEADLINE_S = 90.0


def write_setup(tmp: Path, extra: str = "") -> Path:
    """configs/sim.toml with an absolute calibration path, a shorter lock hold, and ``extra``."""
    text = SIM_TOML.read_text()
    cal = REPO / "configs" / "calibration" / "sim_stereo.json"
    text = text.replace('stereo = "calibration/sim_stereo.json"', f'stereo = "{cal}"')
    text += "\n[procedure.lock]\nhold_s = 0.5\n" + extra
    path = tmp / "setup.toml"
    path.write_text(text)
    return path


async def wait_view(pilot: Pilot[object], app: ConsoleApp, cond: Callable[[ConsoleView], bool],
                    what: str) -> ConsoleView:
    """Let the UI run until the snapshot on screen satisfies ``cond`` (bounded): what the
    operator sees, not merely the controller's latest, which the console shows on its next
    refresh."""
    return await _wait_snapshot(pilot, app, cond, what, on_screen=True)


async def wait_controller(pilot: Pilot[object], app: ConsoleApp, cond: Callable[[ConsoleView], bool],
                          what: str) -> ConsoleView:
    """Let the UI run until the controller's latest snapshot satisfies ``cond`` (bounded),
    whether or not the console has shown it yet (for tests that hold the screen back)."""
    return await _wait_snapshot(pilot, app, cond, what, on_screen=False)


async def _wait_snapshot(pilot: Pilot[object], app: ConsoleApp, cond: Callable[[ConsoleView], bool],
                         what: str, *, on_screen: bool) -> ConsoleView:
    loop = asyncio.get_running_loop()
    end = loop.time() + DEADLINE_S
    while True:
        seen = app.shown_view if on_screen else app.session.runner.latest()
        if seen is not None and cond(seen):
            await pilot.pause()
            return seen
        v = app.session.runner.latest()
        if v is not None and v.error:
            raise AssertionError(f"controller loop failed while waiting for {what}: {v.error}")
        if loop.time() > end:
            raise AssertionError(f"not reached within {DEADLINE_S} s: {what}; last state "
                                 f"{None if v is None else (v.state, v.last_reason, v.faults)}")
        await pilot.pause(0.05)


async def quit_app(pilot: Pilot[object], app: ConsoleApp) -> dict[str, object]:
    """Press q and wait (bounded) for the app to close the session and exit. After the app
    exits the pilot must not be awaited, so this waits on the event loop directly."""
    app.action_quit_console()
    loop = asyncio.get_running_loop()
    end = loop.time() + DEADLINE_S
    while app.return_value is None:
        if loop.time() > end:
            raise AssertionError("console did not exit")
        await asyncio.sleep(0.05)
    rv = app.return_value
    assert isinstance(rv, dict)
    return rv


async def wait_prompt(pilot: Pilot[object], app: ConsoleApp, transition: str) -> None:
    """Wait (bounded) until the console shows the confirmation prompt for ``transition``: the
    screen an operator reads before answering, not merely the controller's snapshot."""
    from hil.console.app import ConfirmScreen

    loop = asyncio.get_running_loop()
    end = loop.time() + DEADLINE_S
    while True:
        screen = app.screen
        if isinstance(screen, ConfirmScreen) and screen.transition_name == transition:
            await pilot.pause()
            return
        v = app.session.runner.latest()
        if v is not None and v.error:
            raise AssertionError(f"controller loop failed while waiting for prompt {transition}: {v.error}")
        if loop.time() > end:
            raise AssertionError(f"prompt {transition} not shown within {DEADLINE_S} s; screen "
                                 f"{type(screen).__name__}; last state "
                                 f"{None if v is None else (v.state, v.pending, v.last_reason)}")
        await pilot.pause(0.05)


async def wait_message(pilot: Pilot[object], app: ConsoleApp, cond: Callable[[str], bool],
                       what: str) -> str:
    """Wait (bounded) until a verdict shown to the operator satisfies ``cond``; returns it."""
    loop = asyncio.get_running_loop()
    end = loop.time() + DEADLINE_S
    while True:
        for m in app.messages:
            if cond(m):
                return m
        if loop.time() > end:
            raise AssertionError(f"no message {what} within {DEADLINE_S} s; shown: {app.messages}")
        await pilot.pause(0.05)


class SessionOpener(Protocol):
    """``open_console_session`` whose sessions the ``open_session`` fixture closes afterwards."""

    def __call__(self, config: str | Path | None, **kwargs: Any) -> ConsoleSession: ...
