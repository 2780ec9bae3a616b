"""The HTML report says how to open the session in the 3D viewer, and names the recording once
``hil replay`` has written it beside the log."""

from __future__ import annotations

import html
import shutil
from pathlib import Path

import pytest

from hil.replay import write_replay
from hil.report import build_report
from hil.report.build import replay_section
from hil.session.log import head_path


@pytest.mark.timeout(400)  # matplotlib's plots take a while on a loaded machine
def test_report_says_how_to_open_the_replay(sim_session: Path, tmp_path: Path) -> None:
    log = tmp_path / sim_session.name
    shutil.copyfile(sim_session, log)
    shutil.copyfile(head_path(sim_session), head_path(log))
    rrd = log.with_suffix(".rrd")
    how = (f"<code>hil replay {html.escape(str(log))}</code> writes "
           f"<code>{html.escape(str(rrd))}</code>")

    before = "\n".join(replay_section(log))
    assert how in before
    assert f"<code>hil replay {html.escape(str(log))} --serve</code>" in before
    assert 'id="replay-file"' not in before

    assert write_replay(log).path == rrd
    page = build_report(log, tmp_path / "report").html_path.read_text(encoding="utf-8")
    assert '<p id="replay">' in page
    assert how in page
    assert (f'<p id="replay-file">Recording written: <code>{html.escape(str(rrd))}</code> '
            f"({rrd.stat().st_size} bytes).</p>") in page
