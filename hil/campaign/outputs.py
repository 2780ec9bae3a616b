"""A campaign's output directory: ``campaign.json``/``campaign.html`` (simulator tier) or
``transport.json``/``transport.html`` (transport tier), and ``logs/`` with the files the runs sent
back (the session logs of failing runs; all with ``--keep-logs``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .report import family_of, pair_row_of, render_html, row_order

#: The summary file's stem per tier.
STEMS = {"simulator": "campaign", "transport": "transport"}


def stem_of(summary: dict[str, Any]) -> str:
    return STEMS[str(summary.get("tier", "simulator"))]


def write_summary(summary: dict[str, Any], out_dir: Path) -> Path:
    """Write ``<stem>.json`` (the ``--json`` object) and ``<stem>.html`` in ``out_dir``; return the
    JSON's path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = stem_of(summary)
    path = out_dir / f"{stem}.json"
    path.write_text(json.dumps(summary, indent=1, default=str) + "\n")
    if stem == "transport":
        from .transport import FAMILIES

        page = render_html(summary, row_of=family_of, order=FAMILIES, title="Transport fault campaign")
    elif summary.get("pairs") is not None:
        rows = row_order(summary["results"], pair_row_of)
        page = render_html(summary, row_of=pair_row_of, order=rows, title="Compound-fault campaign")
    else:
        page = render_html(summary)
    (out_dir / f"{stem}.html").write_text(page)
    return path


class LogSink:
    """Writes the files runs send back under ``out_dir/logs`` (created on the first file)."""

    def __init__(self, out_dir: Path) -> None:
        self.logs = out_dir / "logs"

    def __call__(self, files: dict[str, bytes]) -> None:
        for rel, data in files.items():
            path = self.logs / rel
            if self.logs.resolve() not in path.resolve().parents:
                raise ValueError(f"log file {rel!r} escapes {self.logs}")
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)

    def attach(self, records: list[dict[str, Any]]) -> None:
        """Point each record's ``session_log`` at its file here (None when it was not kept)."""
        for r in records:
            path = self.logs / f"{r['run_id']}.jsonl"
            r["session_log"] = str(path) if path.is_file() else None
