"""The console's panels as text, one pure function each, from a :class:`ConsoleView` (no widget,
no controller: testable alone)."""

from __future__ import annotations

from rich.text import Text

from hil.console.view import WORKFLOW, ConsoleView

_STATE_STYLE = {"fault": "bold white on red", "safe_stop": "bold white on dark_red",
                "paused": "bold black on yellow", "retract": "bold white on dark_orange"}


def mm(x: float | None, digits: int = 3) -> str:
    return "—" if x is None else f"{x:.{digits}f} mm"


def banner_text(v: ConsoleView) -> Text | None:
    """The fault / stop / pause banner with its way out, or None when the procedure is fine."""
    if not (v.error or v.state in ("fault", "safe_stop", "paused")):
        return None
    reason = v.error or v.last_reason or (v.faults[-1] if v.faults else "")
    return Text(f"{v.state.upper()}: {reason}\nway out: {v.hint}")


def workflow_text(v: ConsoleView) -> Text:
    """The procedure's states with the current one lit, the clock, and what comes next."""
    wf = Text()
    for i, s in enumerate(WORKFLOW):
        if i:
            wf.append(" → ", style="dim")
        wf.append(f" {s.value} ", style="bold black on green" if s.value == v.state else "")
    if v.state not in {s.value for s in WORKFLOW}:
        wf.append("   ")
        wf.append(f" {v.state} ", style=_STATE_STYLE.get(v.state, "bold reverse"))
    wf.append(f"   t = {v.t_s:7.2f} s   frames {v.frames}", style="dim")
    wf.append(f"\nnext: {v.hint}", style="italic")
    return wf


def markers_title(located_counts: tuple[int | None, int | None, int] | None) -> str:
    """The marker table's title with the markers located in the latest pair
    (:attr:`ConsoleView.located_counts`: left image, right image, triangulated)."""
    title = "Markers (optical frame)"
    if located_counts is None:
        return title
    left, right, points = ("—" if x is None else str(x) for x in located_counts)
    return f"{title} — located: left {left}, right {right}, 3-D {points}"


def registration_text(v: ConsoleView) -> Text:
    return Text(
        f"FRE            {mm(v.fre_mm)}\n"
        f"expected TRE   {mm(v.tre_expected_mm)}\n"
        f"robot FRE      {mm(v.robot_fre_mm)}\n"
        f"comp. error    {mm(v.comp_error_mm)}" + ("" if v.comp_error_mm is None else " (truth)")
        + breathing_line(v))


def breathing_line(v: ConsoleView) -> str:
    """The registration panel's line on the breathing state at registration (docs/compensation.md):
    how far it moved the plan's entry and target, or why Horn's fit was kept; "" without a 4D
    CT's breathing model."""
    if v.breathing_kept_rigid_because:
        return f"\nbreathing      Horn's fit kept: {v.breathing_kept_rigid_because}"
    if v.breathing_entry_shift_mm is None or v.breathing_target_shift_mm is None:
        return ""
    return (f"\nbreathing      entry moved {mm(v.breathing_entry_shift_mm)}, "
            f"target {mm(v.breathing_target_shift_mm)}")


def robot_text(v: ConsoleView) -> Text:
    tcp = "—" if v.robot_tcp_mm is None else "[" + ", ".join(f"{x:.1f}" for x in v.robot_tcp_mm) + "]"
    robot = Text()
    robot.append("connected      ")
    robot.append("yes" if v.robot_connected else "NO", style="green" if v.robot_connected else "bold red")
    robot.append(f"\nmode           {v.robot_mode}\nsafety         ")
    robot.append(v.robot_safety, style="green" if v.robot_safety == "normal" else "bold red")
    speed = "—" if v.robot_speed_mm_s is None else f"{v.robot_speed_mm_s:.1f} mm/s"
    robot.append(f"\nspeed          {speed}\nTCP (robot)    {tcp}\n"
                 f"guide error    {mm(v.guide_error_mm)}\n"
                 f"commands       {v.commands_sent} sent, {v.commands_refused} refused")
    return robot


def plan_text(v: ConsoleView) -> Text:
    e, t = v.plan_entry_mm, v.plan_target_mm
    return Text(
        f"{v.plan_source}\n{v.plan_fiducials} fiducials\n"
        f"entry  [{e[0]:.1f}, {e[1]:.1f}, {e[2]:.1f}]\ntarget [{t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}]\n"
        f"session log: {v.session_log}\nOpenIGTLink: {v.igtl}")


def gate_text(v: ConsoleView) -> Text:
    gate = Text()
    if v.gate_open:
        gate.append("OPEN", style="bold black on green")
    else:
        gate.append("CLOSED", style="bold white on red")
    dev = v.gate_deviation_mm
    within = dev is not None and dev <= v.gate_tolerance_mm
    gate.append(f"\ndeviation  {mm(dev)}  (tolerance {v.gate_tolerance_mm} mm, dwell {v.gate_dwell_s} s)")
    gate.append("\n" + ("within tolerance" if within else "over tolerance" if dev is not None
                        else "no reference yet (register first)"),
                style="green" if within else "yellow")
    if v.gate_shape_mm is not None or v.gate_worst_marker_mm is not None:
        gate.append(f"\nshape {mm(v.gate_shape_mm)}, farthest marker {mm(v.gate_worst_marker_mm)}")
    if v.change_fre_mm is not None:
        gate.append(f"\nnon-rigid {mm(v.change_fre_mm)} ({v.change_estimator} estimate)")
    if v.target_fallback:
        gate.append(f"\ntarget model: rigid direction kept ({v.target_fallback})", style="yellow")
    elif v.target_shift_mm is not None:
        by = "target sensor" if v.target_source == "sensor" else "target model"
        gate.append(f"\n{by}: target {mm(v.target_shift_mm)} from plan, path turned "
                    f"{v.target_turn_deg or 0.0:.2f} deg")
        if v.target_limited:
            gate.append(f"\n  held at its bounds: {v.target_limited}", style="yellow")
    if v.target_sensor_why_not:
        gate.append(f"\ntarget sensor: none this pair ({v.target_sensor_why_not})", style="yellow")
    return gate


def timeline_text(v: ConsoleView, width: int) -> Text:
    """The last transitions, each cut to ``width`` characters, and the fault count."""
    tl = Text(no_wrap=True)
    for ts, st, why in v.timeline[-8:]:
        tl.append(f"{ts:7.2f} s  {st:<10} {why}"[:width] + "\n")
    if v.faults:
        tl.append(f"faults: {len(v.faults)} (last: {v.faults[-1][:60]})", style="bold red")
    return tl
