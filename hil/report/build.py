"""``hil report``: a session log -> a self-contained ``report.html`` (PNG plots inlined as base64).

Steps: verify the hash chain (:func:`hil.session.verify_session_log`), read the records
(:func:`hil.report.session_data.load_session`), compute the numbers table, render the plots,
write the page. A broken chain does not stop the report: the page says where it breaks in a red
banner (the data after that line cannot be trusted) and the result carries it.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import InputFileError
from hil.report.plots import PLOTS, STATE_COLOURS, Plot
from hil.report.session_data import SessionData, load_session
from hil.session.log import VerifyReport, file_sha256, verify_session_log

Progress = Callable[[str], None]


@dataclass(frozen=True)
class Number:
    """One row of the numbers table: ``key`` (stable id), label, value (None: not available), unit."""

    key: str
    label: str
    value: float | str | None
    unit: str = ""

    def shown(self) -> str:
        if self.value is None:
            return "n/a"
        if isinstance(self.value, float):
            return f"{self.value:.3f}"
        return str(self.value)


@dataclass(frozen=True)
class ReportResult:
    """What :func:`build_report` produced."""

    html_path: Path
    chain: VerifyReport
    numbers: tuple[Number, ...]
    plots: tuple[Plot, ...]
    time_in_state_s: dict[str, float]
    faults: tuple[tuple[float, str], ...]

    def to_dict(self) -> dict[str, Any]:
        return {
            "report": str(self.html_path),
            "chain": {"valid": self.chain.ok, "records": self.chain.records,
                      "first_bad_line": self.chain.first_bad_line, "reason": self.chain.reason,
                      "closed": self.chain.closed, "session_id": self.chain.session_id,
                      "head": self.chain.head},
            "numbers": {n.key: n.value for n in self.numbers},
            "time_in_state_s": {k: round(v, 3) for k, v in self.time_in_state_s.items()},
            "plots": {p.key: ("ok" if p.has_data else "no data") for p in self.plots},
            "faults": [{"t_s": round(t, 3), "reason": r} for t, r in self.faults],
        }


def chain_status(chain: VerifyReport) -> str:
    """One line for people: ``valid``, ``valid (session not closed …)`` or ``broken at line N: …``;
    a valid chain also says whether its last line matches the published chain head (``<log>.head``)."""
    if chain.ok:
        head = {"matched": "; last line matches the published chain head",
                "absent": "; no published chain head (the last line is not covered)"}.get(chain.head, "")
        return "valid" + head + ("" if chain.closed else f" ({chain.reason})")
    if chain.first_bad_line is None:
        return f"invalid: {chain.reason}"
    return f"broken at line {chain.first_bad_line}: {chain.reason}"


def _p95(values: list[float]) -> float | None:
    return float(np.percentile(values, 95)) if values else None


def compute_numbers(data: SessionData) -> tuple[Number, ...]:
    """The numbers table (values in mm, s, or fractions)."""
    comp = np.asarray(data.comp_error_mm.y, dtype=np.float64)
    lock_truth = data.lock_truth_mm.y[-1] if len(data.lock_truth_mm) else None
    lock_deg = data.lock_truth_deg.y[-1] if len(data.lock_truth_deg) else None
    return (
        Number("fre_mm", "FRE (patient registration, RMS)", data.fre_mm, "mm"),
        Number("tre_expected_mm", "Expected TRE at the target", data.tre_expected_mm, "mm"),
        Number("robot_fre_mm", "Robot registration FRE (RMS)", data.robot_fre_mm, "mm"),
        Number("markers", "Markers registered", data.registered_markers, ""),
        Number("lock_error_mm", "Guide error at lock (optical)", data.lock_error_mm(), "mm"),
        Number("lock_truth_error_mm", "Guide error at lock (truth, last)", lock_truth, "mm"),
        Number("lock_truth_direction_deg", "Guide direction error at lock (truth, last)", lock_deg, "deg"),
        Number("target_error_mm", "Guide axis to the true target at lock (truth)",
               data.lock_target_mm.y[0] if len(data.lock_target_mm) else None, "mm"),
        Number("target_error_max_mm", "Guide axis to the true target, max over the hold (truth)",
               max(data.lock_target_mm.y) if len(data.lock_target_mm) else None, "mm"),
        Number("body_rigid_residual_mm_p95", "True skin's rigid-fit residual, 95th percentile (truth)",
               _p95(data.body_residual_mm.y), "mm"),
        Number("change_fre_mm_p95", "Measured change's rigid-fit residual, 95th percentile",
               _p95(data.change_fre_mm.y), "mm"),
        Number("comp_error_rms_mm", "Compensation error RMS (truth)",
               float(np.sqrt(np.mean(comp * comp))) if comp.size else None, "mm"),
        Number("comp_error_p95_mm", "Compensation error 95th percentile (truth)",
               float(np.percentile(comp, 95)) if comp.size else None, "mm"),
        Number("comp_error_max_mm", "Compensation error max (truth)",
               float(comp.max()) if comp.size else None, "mm"),
        Number("gate_open_fraction", "Gate open fraction (of gate samples)", data.gate_open_fraction(), ""),
        Number("target_model_fallback_fraction", "Surrogate target model: compensation pairs it fell back on",
               data.target_model_fallback_fraction(), ""),
        Number("target_model_held_fraction",
               "Surrogate target model: compensation pairs it steered held at a bound",
               data.target_model_held_fraction(), ""),
        Number("target_sensor_fraction", "Target sensor: compensation pairs whose path pointed at its target",
               data.target_sensor_fraction(), ""),
        Number("time_to_lock_s", "Time to lock", data.time_to_lock_s(), "s"),
        Number("duration_s", "Session duration", data.duration_s, "s"),
        Number("faults", "Faults", len(data.faults), ""),
        Number("final_state", "Final state", data.final_state(), ""),
    )


_CSS = """
body{font-family:sans-serif;margin:2em;max-width:1100px;color:#222}
h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.ok{background:#e5f5e0;border:1px solid #74c476;padding:.6em}
.bad{background:#fee0d2;border:1px solid #de2d26;padding:.6em;font-weight:bold}
figure{margin:1em 0}figcaption{font-size:.9em;color:#555}img{max-width:100%}
.swatch{display:inline-block;width:.9em;height:.9em;vertical-align:middle;margin-right:.3em}
"""


def _esc(x: object) -> str:
    return html.escape(str(x), quote=True)


def replay_section(log: Path) -> list[str]:
    """How to open the session in the 3D viewer (``hil replay``, docs/replay.md), and the
    recording's path when one has been written beside the log (``<log>.rrd``)."""
    from hil.replay.recording import default_out_path

    rrd = default_out_path(log)
    out = ["<h2>3D replay</h2>",
           '<p id="replay">Scrub through this session in 3D (markers, arm, guide axis, plan, '
           "transitions, following error, latency, gate deviation) in the Rerun viewer: "
           f"<code>hil replay {_esc(log)}</code> writes <code>{_esc(rrd)}</code>; open it with "
           f"<code>rerun {_esc(rrd)}</code>, or serve it to a browser on this machine with "
           f"<code>hil replay {_esc(log)} --serve</code>.</p>"]
    if rrd.is_file():
        out.append(f'<p id="replay-file">Recording written: <code>{_esc(rrd)}</code> '
                   f"({rrd.stat().st_size} bytes).</p>")
    return out


def render_html(data: SessionData, chain: VerifyReport, numbers: tuple[Number, ...],
                plots: tuple[Plot, ...], log_sha256: str) -> str:
    """The whole page as one string (no external resources)."""
    h = data.header
    status = chain_status(chain)
    banner_cls = "ok" if chain.ok else "bad"
    out: list[str] = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f"<title>Session report {_esc(h.get('session_id', ''))}</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>Session report</h1>",
        f'<p class="{banner_cls}" id="chain" data-valid="{str(chain.ok).lower()}">'
        f"Hash chain: {_esc(status)} ({chain.records} records verified)</p>",
        '<table id="session">',
    ]
    info = [("log file", str(data.path)), ("log SHA-256", log_sha256),
            ("session id", h.get("session_id")), ("started (wall, UTC)", h.get("wall")),
            ("setup", h.get("setup") or h.get("name")), ("config SHA-256", h.get("config_sha256")),
            ("calibration SHA-256", h.get("calibration_sha256")),
            ("records", data.records), ("closed normally", "yes" if data.closed else "no")]
    for label, value in info:
        if value is not None:
            out.append(f"<tr><th>{_esc(label)}</th><td>{_esc(value)}</td></tr>")
    out.append("</table>")

    out.append("<h2>Numbers</h2>")
    out.append('<table id="numbers"><tr><th>figure</th><th>value</th><th>unit</th></tr>')
    for n in numbers:
        out.append(f'<tr data-key="{_esc(n.key)}"><td>{_esc(n.label)}</td>'
                   f'<td class="num">{_esc(n.shown())}</td><td>{_esc(n.unit)}</td></tr>')
    out.append("</table>")

    out.append("<h2>Time in each state</h2>")
    out.append('<table id="time_in_state"><tr><th>state</th><th>time (s)</th></tr>')
    for s, sec in data.time_in_state_s().items():
        colour = STATE_COLOURS.get(s, "#888888")
        out.append(f'<tr data-key="{_esc(s)}"><td><span class="swatch" style="background:{colour}"></span>'
                   f'{_esc(s)}</td><td class="num">{sec:.3f}</td></tr>')
    out.append("</table>")

    out.append("<h2>Plots</h2>")
    for p in plots:
        b64 = base64.b64encode(p.png).decode("ascii")
        cap = p.title + ("" if p.has_data else " — no data") + (f" ({p.note})" if p.note else "")
        out.append(f'<figure data-plot="{_esc(p.key)}" data-has-data="{str(p.has_data).lower()}">'
                   f'<img alt="{_esc(p.title)}" src="data:image/png;base64,{b64}">'
                   f"<figcaption>{_esc(cap)}</figcaption></figure>")

    out.append("<h2>Faults</h2>")
    if data.faults:
        out.append('<table id="faults"><tr><th>time (s)</th><th>reason</th></tr>')
        for t, r in data.faults:
            out.append(f'<tr><td class="num">{t:.3f}</td><td>{_esc(r)}</td></tr>')
        out.append("</table>")
    else:
        out.append('<p id="faults">No faults.</p>')

    out.extend(replay_section(data.path))
    out.append("<h2>Transitions</h2>")
    out.append('<table id="transitions">'
               "<tr><th>time (s)</th><th>transition</th><th>from</th><th>to</th></tr>")
    for t, name, src, dst in data.transitions:
        out.append(f'<tr><td class="num">{t:.3f}</td><td>{_esc(name)}</td><td>{_esc(src)}</td>'
                   f"<td>{_esc(dst)}</td></tr>")
    out.append("</table></body></html>")
    return "\n".join(out) + "\n"


def build_report(log_path: str | Path, out_dir: str | Path | None = None,
                 progress: Progress | None = None) -> ReportResult:
    """Build ``<out_dir>/report.html`` (default: ``<log dir>/<log stem>_report/``).

    Blocking; minutes at most for very long logs (progress lines go to ``progress``).

    Raises:
        InputFileError: the log cannot be read or holds a malformed record (names file and
            line); the output directory cannot be written.
    """
    say = progress or (lambda _msg: None)
    log = Path(log_path)
    out = Path(out_dir) if out_dir is not None else log.parent / f"{log.stem}_report"
    say(f"verifying hash chain of {log}")
    chain = verify_session_log(log)
    say(f"hash chain {chain_status(chain)}")
    data = load_session(log, say)
    say(f"read {data.records} records, {data.duration_s:.1f} s of session")
    numbers = compute_numbers(data)
    plots: list[Plot] = []
    for k, (key, fn) in enumerate(PLOTS, 1):
        say(f"plot {k}/{len(PLOTS)}: {key}")
        plots.append(fn(data))
    page = render_html(data, chain, numbers, tuple(plots), file_sha256(log))
    try:
        out.mkdir(parents=True, exist_ok=True)
        html_path = out / "report.html"
        html_path.write_text(page, encoding="utf-8")
    except OSError as exc:
        raise InputFileError(str(out), f"cannot write the report: {exc.strerror or exc}") from None
    say(f"wrote {html_path}")
    return ReportResult(html_path, chain, numbers, tuple(plots), data.time_in_state_s(), tuple(data.faults))

