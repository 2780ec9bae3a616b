"""Fixtures for the console tests: every console session a test opens is closed on every path
(its controller thread stopped, devices, OpenIGTLink server and session log closed), so a failing
test leaves no controller thread running into the next test or the interpreter's exit."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hil.console.session import ConsoleSession, open_console_session
from tests.operator.console_helpers import SessionOpener


@pytest.fixture
def open_session() -> Iterator[SessionOpener]:
    opened: list[ConsoleSession] = []

    def opener(config: str | Path | None, **kwargs: Any) -> ConsoleSession:
        session = open_console_session(config, **kwargs)
        opened.append(session)
        return session

    yield opener
    for session in opened:
        session.close()  # idempotent; the loop aborts a procedure under way first
        assert session.runner.ended, "the console's controller thread did not stop"
