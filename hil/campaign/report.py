"""The campaign's summary: the scenario x state table (stdout), JSON and HTML files."""

from __future__ import annotations

import html
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

from hil.config.faults import FaultKind

from .scenarios import TARGET_STATES


def summarise(results: list[dict[str, Any]], *, config: str) -> dict[str, Any]:
    """The ``--json`` object: counts, worst latency, failing runs with their replay command."""
    fault_runs = [r for r in results if r.get("kind")]
    lat = [r["safe_latency_ms"] for r in fault_runs if isinstance(r.get("safe_latency_ms"), int | float)]
    failing = [
        {
            "scenario": r["scenario"],
            "seed": r["seed"],
            "reasons": r.get("reasons", []),
            "outcome": r.get("outcome"),
            "session_log": r.get("session_log"),
            "replay": r.get("replay") or (
                f"hil campaign {r['scenario']} --seed {r['seed']} --config {config}"
                if r.get("kind")
                else f"hil run {config} --seed {r['seed']} --auto"
            ),
        }
        for r in results
        if not r.get("passed")
    ]
    outcomes: dict[str, int] = defaultdict(int)
    for r in results:
        outcomes[str(r.get("outcome"))] += 1
    return {
        "runs": len(results),
        "passed": sum(1 for r in results if r.get("passed")),
        "failed": len(failing),
        "worst_safe_latency_ms": max(lat) if lat else None,
        "worst_stop_latency_ms": max(
            (r["stop_latency_ms"] for r in fault_runs if isinstance(r.get("stop_latency_ms"), int | float)),
            default=None,
        ),
        "limit_violations": sum(len(r.get("limit_violations", [])) for r in results),
        "outcomes": dict(outcomes),
        "failing": failing,
        "config": config,
        "results": results,
    }


RowOf = Callable[[dict[str, Any]], str]


def kind_of(result: dict[str, Any]) -> str:
    """The simulator tier's table row: the fault kind."""
    return str(result["kind"])


def family_of(result: dict[str, Any]) -> str:
    """The transport tier's table row: the fault family (the scenario name before ``@``)."""
    return str(result["scenario"]).partition("@")[0]


def pair_row_of(result: dict[str, Any]) -> str:
    """The pairs campaign's table row: ``A+B`` (overlapping), ``A+B+recovery`` (the second fault in
    the recovery from the first), or the kind of a single-fault placement run."""
    name = str(result["scenario"])
    head = name.partition("@")[0]
    return head + ("+recovery" if name.endswith("+recovery") else "")


def row_order(results: list[dict[str, Any]], row_of: RowOf) -> list[str]:
    """The rows of ``results`` in the order they first appear (baselines left out)."""
    out: list[str] = []
    for r in results:
        if r.get("kind") and row_of(r) not in out:
            out.append(row_of(r))
    return out


def _cells(results: list[dict[str, Any]], row_of: RowOf = kind_of,
           ) -> dict[tuple[str, str], tuple[int, int, float | None]]:
    """(row, state) -> (runs, failed, worst latency ms); rows are fault kinds unless ``row_of``
    says otherwise."""
    acc: dict[tuple[str, str], list[Any]] = defaultdict(lambda: [0, 0, None])
    for r in results:
        if not r.get("kind"):
            continue
        c = acc[(row_of(r), r["state"])]
        c[0] += 1
        c[1] += 0 if r.get("passed") else 1
        lat = r.get("safe_latency_ms")
        if isinstance(lat, int | float):
            c[2] = lat if c[2] is None else max(c[2], lat)
    return {k: (v[0], v[1], v[2]) for k, v in acc.items()}


def _cell_text(cell: tuple[int, int, float | None] | None) -> str:
    if cell is None:
        return "-"
    runs, failed, lat = cell
    verdict = "pass" if failed == 0 else f"FAIL {failed}/{runs}"
    return verdict + ("" if lat is None else f" {round(lat)}ms")  # an int: never "-0ms"


def _rows(cells: dict[tuple[str, str], Any], order: Sequence[str] | None) -> list[str]:
    names = [k.value for k in FaultKind] if order is None else list(order)
    return [k for k in names if any(key[0] == k for key in cells)]


def table(results: list[dict[str, Any]], *, row_of: RowOf = kind_of,
          order: Sequence[str] | None = None) -> str:
    """Fault (kind, or ``row_of`` of a result, in ``order``) x state: pass/fail and the worst
    safe-state latency."""
    cells = _cells(results, row_of)
    kinds = _rows(cells, order)
    states = [s for s in TARGET_STATES if any(key[1] == s for key in cells)]
    w0 = max([len("fault \\ state"), *(len(k) for k in kinds)])
    cols = [max(len(s), *(len(_cell_text(cells.get((k, s)))) for k in kinds)) for s in states]
    lines = [
        "  ".join(["fault \\ state".ljust(w0), *(s.ljust(w) for s, w in zip(states, cols, strict=True))])
        .rstrip()
    ]
    for k in kinds:
        lines.append(
            "  ".join(
                [
                    k.ljust(w0),
                    *(_cell_text(cells.get((k, s))).ljust(w) for s, w in zip(states, cols, strict=True)),
                ]
            ).rstrip()
        )
    return "\n".join(lines) + "\n"


def _second_text(r: dict[str, Any]) -> str:
    """A compound-fault run's second fault: kind, onset, state hit, safe state and latency."""
    if not r.get("second_kind"):
        return ""
    text = f"{r['second_kind']} at {r.get('second_onset_s')} s in {r.get('second_state_at_onset')}"
    if r.get("second_safe_state"):
        text += f" -> {r['second_safe_state']} {r.get('second_safe_latency_ms')} ms"
    return text


def render_html(summary: dict[str, Any], *, row_of: RowOf = kind_of, order: Sequence[str] | None = None,
                title: str = "Fault-injection campaign") -> str:
    """The summary as one HTML page: the fault x state table (rows as in :func:`table`), the
    failing runs with their replay commands, every run."""
    results = summary["results"]
    cells = _cells(results, row_of)
    kinds = _rows(cells, order)
    states = [s for s in TARGET_STATES if any(key[1] == s for key in cells)]
    e = html.escape
    compound = any(r.get("second_kind") for r in results)

    def td(cell: tuple[int, int, float | None] | None) -> str:
        colour = "#eee" if cell is None else ("#c8f0c8" if cell[1] == 0 else "#f4c2c2")
        return f'<td style="background:{colour}">{e(_cell_text(cell))}</td>'

    rows = "".join(f"<tr><th>{e(k)}</th>{''.join(td(cells.get((k, s))) for s in states)}</tr>" for k in kinds)
    fails = "".join(
        f"<tr><td>{e(f['scenario'])}</td><td>{f['seed']}</td><td>{e('; '.join(f['reasons']))}</td>"
        f"<td><code>{e(f['replay'])}</code></td></tr>"
        for f in summary["failing"]
    )
    runs = "".join(
        f"<tr><td>{e(r['scenario'])}</td><td>{r['seed']}</td><td>{'pass' if r['passed'] else 'FAIL'}</td>"
        f"<td>{e(str(r.get('outcome')))}</td><td>{e(str(r.get('state_at_onset')))}</td>"
        f"<td>{e(str(r.get('safe_state')))}</td><td>{e(str(r.get('safe_latency_ms')))}</td>"
        f"<td>{e(str(r.get('stop_latency_ms')))}</td><td>{e(str(r.get('recovered_to_lock')))}</td>"
        f"<td>{e(str(r.get('final_state')))}</td>"
        + (f"<td>{e(_second_text(r))}</td>" if compound else "") + "</tr>"
        for r in results
    )
    head = (
        f"<p>{summary['runs']} runs, {summary['passed']} passed, {summary['failed']} failed; worst "
        f"safe-state latency {summary['worst_safe_latency_ms']} ms; config {e(summary['config'])}</p>"
    )
    return (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{e(title)}</title>"
        "<style>body{font-family:sans-serif}td,th{border:1px solid #999;padding:2px 6px}"
        "table{border-collapse:collapse;margin-bottom:1em}</style></head><body>"
        f"<h1>{e(title)}</h1>{head}"
        f"<h2>Fault x state</h2><table><tr><th>fault \\ state</th>"
        f"{''.join(f'<th>{e(s)}</th>' for s in states)}</tr>{rows}</table>"
        f"<h2>Failing runs</h2><table><tr><th>scenario</th><th>seed</th><th>reasons</th><th>replay</th></tr>"
        f"{fails}</table>"
        "<h2>All runs</h2><table><tr><th>scenario</th><th>seed</th><th>verdict</th><th>outcome</th>"
        "<th>state at onset</th><th>safe state</th><th>latency ms</th><th>stop ms</th>"
        "<th>recovered to lock</th><th>final</th>" + ("<th>second fault</th>" if compound else "")
        + "</tr>" + runs + "</table></body></html>\n"
    )
