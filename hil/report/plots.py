"""The report's plots, rendered to PNG bytes with matplotlib's Agg canvas (no display, no pyplot
global state, safe in any thread).

Each function takes :class:`~hil.report.session_data.SessionData` and returns a
:class:`Plot`; missing data gives a plot that says "no data" (``has_data`` False), never an
error. Every time-axis plot marks the faults (red dashed lines) on the session time axis.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from hil.report.session_data import SessionData

#: Colours of the states on the timeline (stable across reports).
STATE_COLOURS: dict[str, str] = {
    "idle": "#bdbdbd", "register": "#6baed6", "plan": "#9e9ac8", "approach": "#fdae6b",
    "gate": "#fdd0a2", "compensate": "#74c476", "lock": "#238b45", "paused": "#ffd92f",
    "retract": "#e6550d", "fault": "#de2d26", "safe_stop": "#a50f15", "done": "#31a354",
}
_STATE_ORDER = list(STATE_COLOURS)


@dataclass(frozen=True)
class Plot:
    """One rendered plot: ``key`` (stable id), ``title``, PNG bytes, and whether it had data."""

    key: str
    title: str
    png: bytes
    has_data: bool
    note: str = ""


def _figure(height_in: float = 2.8) -> tuple[Figure, Axes]:
    fig = Figure(figsize=(10.0, height_in), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    return fig, ax


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _no_data(fig: Figure, ax: Axes, key: str, title: str, why: str) -> Plot:
    """The plot ``key`` saying "no data" and why (``has_data`` False)."""
    ax.text(0.5, 0.5, f"no data\n{why}", ha="center", va="center", transform=ax.transAxes,
            fontsize=12, color="#666666")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title)
    return Plot(key, title, _png(fig), False)


def _mark_faults(ax: Axes, data: SessionData, label: bool = True) -> None:
    for i, (t, _reason) in enumerate(data.faults):
        ax.axvline(t, color="#de2d26", linestyle="--", linewidth=1.2,
                   label="fault" if (label and i == 0) else None)


def _time_axis(ax: Axes, data: SessionData) -> None:
    ax.set_xlim(0.0, max(data.duration_s, 1e-3))
    ax.set_xlabel("session time (s)")
    ax.grid(True, alpha=0.3)


def plot_state_timeline(data: SessionData) -> Plot:
    fig, ax = _figure(2.6)
    intervals = data.state_intervals()
    seen = [s for s in _STATE_ORDER if any(i[0] == s for i in intervals)]
    seen += sorted({i[0] for i in intervals} - set(seen))
    rows = {s: k for k, s in enumerate(seen)}
    for s, a, b in intervals:
        colour = STATE_COLOURS.get(s, "#888888")
        ax.broken_barh([(a, max(b - a, data.duration_s * 0.002))], (rows[s] - 0.4, 0.8), facecolors=colour)
        if b - a <= data.duration_s * 0.01:  # a state entered at the very end (done, safe_stop)
            ax.plot([a], [rows[s]], marker="D", color=colour, markeredgecolor="#333333", markersize=7,
                    clip_on=False)
    ax.set_yticks(range(len(seen)), seen)
    ax.invert_yaxis()
    _time_axis(ax, data)
    _mark_faults(ax, data)
    for t, reason in data.faults:
        ax.annotate(reason[:40], (t, -0.5), xytext=(3, 0), textcoords="offset points", fontsize=7,
                    color="#a50f15", va="bottom", annotation_clip=False)
    ax.set_title("procedure states")
    return Plot("states", "State timeline", _png(fig), True)


def plot_breathing(data: SessionData) -> Plot:
    fig, ax = _figure()
    key, title = "breathing", "Breathing trace and hold-breath gate"
    if not len(data.breathing_mm):
        return _no_data(fig, ax, key, title, "no gate or compensation measurements in this session")
    for i, (a, b) in enumerate(data.gate_open_intervals()):
        ax.axvspan(a, b, color="#74c476", alpha=0.25, label="gate open" if i == 0 else None)
    for i, (a, b) in enumerate(data.gate_closed_intervals()):
        ax.axvspan(a, b, color="#fb6a4a", alpha=0.2, label="gate closed" if i == 0 else None)
    t, y = data.breathing_mm.arrays()
    ax.plot(t, y, ".-", color="#08519c", markersize=2, linewidth=0.8, label="deviation from reference (RMS)")
    if data.gate_tolerance_mm is not None:
        ax.axhline(data.gate_tolerance_mm, color="#444444", linestyle=":", label="gate tolerance")
    _time_axis(ax, data)
    _mark_faults(ax, data)
    ax.set_ylabel("mm")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=7)
    return Plot(key, title, _png(fig), True)


def plot_errors(data: SessionData) -> Plot:
    fig, ax = _figure()
    key, title = "errors", "Guide error and compensation error"
    if not len(data.guide_error_mm) and not len(data.comp_error_mm) and not len(data.lock_truth_mm):
        return _no_data(fig, ax, key, title, "the guide never reached the patient in this session")
    if len(data.guide_error_mm):
        t, y = data.guide_error_mm.arrays()
        ax.plot(t, y, ".", color="#08519c", markersize=3, label="guide error (optical)")
    if len(data.comp_error_mm):
        t, y = data.comp_error_mm.arrays()
        ax.plot(t, y, "-", color="#e6550d", linewidth=1.0, label="compensation error (truth)")
    if len(data.lock_truth_mm):
        t, y = data.lock_truth_mm.arrays()
        ax.plot(t, y, "-", color="#238b45", linewidth=1.0, label="error while locked (truth)")
    if data.lock_tolerance_mm is not None:
        ax.axhline(data.lock_tolerance_mm, color="#444444", linestyle=":", label="lock tolerance")
    note = "" if len(data.comp_error_mm) or len(data.lock_truth_mm) else \
        "no ground truth (compensation error needs the simulator)"
    _time_axis(ax, data)
    _mark_faults(ax, data)
    ax.set_ylabel("mm")
    ax.set_title(title + (f" — {note}" if note else ""))
    ax.legend(loc="upper right", fontsize=7)
    return Plot(key, title, _png(fig), True, note)


def plot_marker_residuals(data: SessionData) -> Plot:
    fig, ax = _figure()
    key, title = "residuals", "Marker residuals"
    series = {i: s for i, s in data.marker_residuals_mm.items() if len(s)}
    if series:
        for i, s in sorted(series.items()):
            t, y = s.arrays()
            ax.plot(t, y, "-", linewidth=0.9, label=f"marker {i}")
        _time_axis(ax, data)
        _mark_faults(ax, data)
        ax.set_ylabel("residual to the registered set (mm)")
        ax.legend(loc="upper right", fontsize=7, ncol=4)
        ax.set_title(title + " over time")
        return Plot(key, title, _png(fig), True)
    res = data.registration_residuals_mm
    if res:
        ax.bar(range(len(res)), res, color="#6baed6")
        ax.set_xticks(range(len(res)))
        ax.set_xlabel("marker")
        ax.set_ylabel("residual at registration (mm)")
        if data.fre_mm is not None:
            ax.axhline(data.fre_mm, color="#444444", linestyle=":", label="FRE (RMS)")
            ax.legend(loc="upper right", fontsize=7)
        ax.set_title(title + " at registration")
        return Plot(key, title, _png(fig), True, "at registration only")
    return _no_data(fig, ax, key, title, "the log has no per-marker residuals")


def plot_body_state(data: SessionData) -> Plot:
    """The body against its registered state (the gate's and lock's judgement, issue 41): each
    skin marker's distance from its reference position, the shape residual after removing a
    rigid motion, and the measured change's rigid-fit residual per pair (mm)."""
    fig, ax = _figure()
    key, title = "body", "Body state: per-marker deviations and shape"
    deviations = {i: s for i, s in data.marker_deviations_mm.items() if len(s)}
    if not deviations and not len(data.shape_mm) and not len(data.change_fre_mm):
        return _no_data(fig, ax, key, title, "the log has no per-marker deviations or shape residuals")
    for i, s in sorted(deviations.items()):
        t, y = s.arrays()
        ax.plot(t, y, "-", linewidth=0.6, alpha=0.7, label=f"marker {i} deviation")
    if len(data.shape_mm):
        t, y = data.shape_mm.arrays()
        ax.plot(t, y, ".", color="#000000", markersize=2.5, label="shape residual (rigid removed)")
    if len(data.change_fre_mm):
        t, y = data.change_fre_mm.arrays()
        ax.plot(t, y, "--", color="#756bb1", linewidth=1.0, label="change fit residual (per pair)")
    _time_axis(ax, data)
    _mark_faults(ax, data)
    ax.set_ylabel("mm")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=6, ncol=3)
    return Plot(key, title, _png(fig), True)


#: fallback reasons named in the target model plot's legend (the commonest first)
_FALLBACK_REASONS_SHOWN = 3


def plot_target_model(data: SessionData) -> Plot:
    """The surrogate target model per pair (issue 41, docs/compensation.md "The direction"): the
    turn it added to the path's direction (deg) and the modelled target's shift from the plan's
    (mm, right axis), and a red mark at each pair it fell back on (kept the rigid direction), the
    commonest reasons in the legend with their counts."""
    fig, ax = _figure()
    key, title = "target", "Target model: turn, shift and fallbacks"
    if not len(data.target_turn_deg):
        return _no_data(fig, ax, key, title, "the session ran without the surrogate target model")
    t, turn = data.target_turn_deg.arrays()
    ax.plot(t, turn, "-", color="#3182bd", linewidth=0.9, label="turn added (deg)")
    ax.set_ylabel("turn (deg)")
    if len(data.target_shift_mm):
        right = ax.twinx()
        ts, shift = data.target_shift_mm.arrays()
        right.plot(ts, shift, "-", color="#31a354", linewidth=0.8, alpha=0.8, label="target shift (mm)")
        right.set_ylabel("target shift (mm)")
        right.legend(loc="upper left", fontsize=7)
    counts: dict[str, int] = {}
    for _, why in data.target_fallbacks:
        counts[why] = counts.get(why, 0) + 1
    if data.target_fallbacks:
        tf = [tt for tt, _ in data.target_fallbacks]
        shown = sorted(counts.items(), key=lambda kv: -kv[1])[:_FALLBACK_REASONS_SHOWN]
        label = "fell back: " + "; ".join(f"{why[:50]} (x{n})" for why, n in shown)
        ax.plot(tf, [0.0] * len(tf), "x", color="#de2d26", markersize=5, label=label)
    if data.target_held:
        th = [tt for tt, _ in data.target_held]
        ax.plot(th, [0.0] * len(th), "|", color="#fd8d3c", markersize=6,
                label=f"held at a bound (x{len(th)}): score beyond the 4D CT's range or turn at its bound")
    _time_axis(ax, data)
    _mark_faults(ax, data)
    note = (f"fell back on {len(data.target_fallbacks)} of {len(turn)} pairs, "
            f"held at a bound on {len(data.target_held)}")
    ax.set_title(f"{title} ({note})")
    ax.legend(loc="upper right", fontsize=6)
    return Plot(key, title, _png(fig), True, note)


def plot_robot_speed(data: SessionData) -> Plot:
    fig, ax = _figure()
    key, title = "speed", "Robot speed"
    if not len(data.robot_speed_mm_s):
        return _no_data(fig, ax, key, title, "no robot speed or motion commands in this session")
    t, y = data.robot_speed_mm_s.arrays()
    ax.plot(t, y, ".-", color="#e6550d", markersize=2, linewidth=0.8,
            label=f"TCP speed ({data.robot_speed_kind})")
    _time_axis(ax, data)
    _mark_faults(ax, data)
    ax.set_ylabel("mm/s")
    ax.set_title(title + f" ({data.robot_speed_kind})")
    ax.legend(loc="upper right", fontsize=7)
    return Plot(key, title, _png(fig), True, data.robot_speed_kind)


#: The report's plots, in page order.
PLOTS: tuple[tuple[str, Callable[[SessionData], Plot]], ...] = (
    ("states", plot_state_timeline),
    ("breathing", plot_breathing),
    ("errors", plot_errors),
    ("residuals", plot_marker_residuals),
    ("body", plot_body_state),
    ("target", plot_target_model),
    ("speed", plot_robot_speed),
)
