"""``hil console --viewer``: the console session streams to Rerun and closes the stream with
the session (its counts in the summary); a bad target is refused before anything starts."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from hil.console.session import open_console_session
from hil.errors import InputFileError
from tests.replay.conftest import live_chunks


def test_console_session_streams_and_closes_the_viewer(tmp_path: Path) -> None:
    rrd = tmp_path / "console.rrd"
    session = open_console_session(None, session_dir=tmp_path, fast=True, viewer=str(rrd))
    try:
        assert session.viewer is not None
        assert [t.name for t in threading.enumerate()].count("hil-viewer") == 1
    finally:
        summary = session.close()
    counts = summary["viewer"]
    assert counts["offered"] == counts["written"] + counts["dropped"] + counts["write_errors"] \
        + counts["lost_on_close"]
    assert counts["write_errors"] == 0
    assert "hil-viewer" not in [t.name for t in threading.enumerate()]
    assert live_chunks(rrd)  # a readable recording, even of a session closed at once


def test_console_refuses_a_viewer_file_in_a_missing_directory(tmp_path: Path) -> None:
    target = tmp_path / "missing" / "x.rrd"
    with pytest.raises(InputFileError, match="the recording's directory does not exist"):
        open_console_session(None, session_dir=tmp_path, fast=True, viewer=str(target))
    assert "hil-viewer" not in [t.name for t in threading.enumerate()]
    assert not list(tmp_path.glob("session_*.jsonl"))
