"""A simulated run shared by the replay tests (once per module: it takes a few seconds)."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import pytest

from hil.cli import main


@pytest.fixture(scope="module")
def sim_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The session log of a default simulated ``hil run --json`` (auto-confirmed, seed 7)."""
    d = tmp_path_factory.mktemp("session")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["run", "--json", "--no-report", "--session-dir", str(d)])
    assert code == 0, out.getvalue()
    summary = json.loads(out.getvalue())
    assert summary["final_state"] == "done"
    return Path(summary["session_log"])


def read_records(log: Path) -> list[dict[str, Any]]:
    """The records of a session log, parsed here (independently of hil's reader)."""
    return [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]


def live_chunks(rrd: Path) -> list[Any]:
    """The chunks of a live stream's ``.rrd``, read as Rerun's reader streams them; asserts that
    the file has no footer, as the live stream writes it (hil.replay.live: bounded memory)."""
    from rerun.chunk import RrdReader
    from rerun.error_utils import RerunWarning

    with pytest.warns(RerunWarning, match="no footer"):
        reader = RrdReader(rrd)
    return list(reader.stream())
