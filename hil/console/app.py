"""The operator console: a textual TUI over a running :class:`ConsoleSession`.

The UI only *reads* snapshots (:class:`~hil.console.view.ConsoleView`) the controller thread
publishes, on a 10 Hz timer, and only *posts* operator commands to the controller's queue. It
never calls the robot, never changes the state machine directly and never waits on the
controller loop: every command the operator gives goes through the state machine and the
safety layer exactly like ``hil run``'s.
"""

from __future__ import annotations

from typing import Any, ClassVar

from rich.text import Text
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.widgets import Button, DataTable, Footer, Header, Sparkline, Static

from hil.console.confirm import CONFIRM_TEXT, Answer, ConfirmScreen
from hil.console.keys import COMMANDS, NOT_NOW_KEY, NOT_NOW_LABEL, QUIT_KEY
from hil.console.panels import (
    banner_text,
    gate_text,
    markers_title,
    plan_text,
    registration_text,
    robot_text,
    timeline_text,
    workflow_text,
)
from hil.console.session import ConsoleSession
from hil.console.view import ConsoleView
from hil.controller.fsm import Event
from hil.controller.operator_input import CommandResult

REFRESH_HZ = 10.0
#: Operator messages kept on screen (the newest last).
MESSAGES_SHOWN = 3

__all__ = ["COMMANDS", "CONFIRM_TEXT", "ConfirmScreen", "ConsoleApp", "gate_windows"]

def gate_windows(samples: tuple[float, ...], tolerance_mm: float, width: int) -> Text:
    """A strip under the breathing sparkline: green where the deviation was within the gate
    tolerance, red where it was over, bucketed like the sparkline (max per bucket)."""
    out = Text(no_wrap=True)
    n = len(samples)
    if n == 0:
        return out.append("no breathing data yet (register first)", style="dim")
    for k in range(width):
        lo, hi = k * n // width, max((k + 1) * n // width, k * n // width + 1)
        chunk = samples[lo:min(hi, n)]
        if not chunk:
            continue
        ok = max(chunk) <= tolerance_mm
        out.append("▀", style="green" if ok else "red")
    return out


class ConsoleApp(App[dict[str, Any]]):
    """The console. ``session`` is already running (its controller thread ticks on its own)."""

    TITLE = "needle-guide HIL console"
    CSS = """
    #banner { display: none; height: auto; padding: 0 1; background: $error; color: $text; text-style: bold; }
    #banner.shown { display: block; }
    #messages { height: auto; padding: 0 1; color: $warning; }
    #workflow { height: auto; padding: 0 1; }
    #main { height: 1fr; }
    #left { width: 44; }
    #mid { width: 1fr; }
    #right { width: 46; }
    .panel { border: round $primary; height: auto; padding: 0 1; }
    #markers { height: 1fr; border: round $primary; }
    #breathing { height: 4; border: round $primary; border-bottom: none; }
    #gatebar { height: 2; border: round $primary; border-top: none; padding: 0 0; }
    #buttons { height: 3; }
    #buttons Button { min-width: 10; margin: 0 1 0 0; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        *[Binding(k, f"command('{k}')", label) for k, (_e, label) in COMMANDS.items()],
        # n outside a prompt (after "not now"): decline the confirmation shown again; in the
        # footer only while a confirmation is on the workflow line
        Binding(NOT_NOW_KEY, "not_now", NOT_NOW_LABEL),
        Binding(QUIT_KEY, "quit_console", "Quit"),
    ]

    def __init__(self, session: ConsoleSession) -> None:
        super().__init__()
        self.session = session
        self._hil_shown: ConsoleView | None = None
        self._hil_prompted: str | None = None
        self._hil_confirm: ConfirmScreen | None = None
        self._hil_quitting = False
        #: every verdict shown to the operator, oldest first (the last few are on screen)
        self.messages: list[str] = []
        self.summary: dict[str, Any] | None = None
        self.sub_title = f"{session.setup.name or session.config_path.name} — plan {session.plan.source}"

    # ---------------------------------------------------------------- layout
    def compose(self) -> ComposeResult:
        yield Header()
        yield Static(id="banner")
        yield Static(id="workflow")
        yield Static(id="messages")
        with Horizontal(id="main"):
            with Vertical(id="left"):
                yield Static(id="registration", classes="panel")
                yield Static(id="robot", classes="panel")
                yield Static(id="plan", classes="panel")
            with Vertical(id="mid"):
                yield DataTable(id="markers", zebra_stripes=True, cursor_type="none")
            with Vertical(id="right"):
                yield Static(id="gate", classes="panel")
                yield Sparkline([], id="breathing", summary_function=max)
                yield Static(id="gatebar")
                yield Static(id="timeline", classes="panel")
        with Horizontal(id="buttons"):
            for key, (_e, label) in COMMANDS.items():
                yield Button(f"{label} ({key})", id=f"cmd-{key}")
            yield Button(f"Quit ({QUIT_KEY})", id=f"cmd-{QUIT_KEY}", variant="error")
        yield Footer()

    def on_mount(self) -> None:
        table = self.query_one("#markers", DataTable)
        table.border_title = "Markers (optical frame)"
        table.add_columns("marker", "x mm", "y mm", "z mm", "residual", "from ref", "seen")
        for pid, title in (("registration", "Registration"), ("robot", "Robot"), ("plan", "Plan"),
                           ("gate", "Hold-breath gate"), ("timeline", "Timeline")):
            self.query_one(f"#{pid}", Static).border_title = title
        self.query_one("#breathing", Sparkline).border_title = "breathing: deviation from reference"
        self.refresh_timer = self.set_interval(1.0 / REFRESH_HZ, self.refresh_view)
        self.refresh_view()

    # ---------------------------------------------------------------- commands
    def _shown_pending(self) -> str:
        """The confirmation the operator has on screen ("" when none): what a confirm names."""
        if self._hil_confirm is not None:
            return self._hil_confirm.transition_name
        v = self._hil_shown
        return "" if v is None or v.pending is None else v.pending

    def action_command(self, key: str, origin: str = "") -> None:
        """Post one operator command; the controller's verdict is shown when it comes back."""
        event, _label = COMMANDS[key]
        confirms = self._shown_pending() if event is Event.CONFIRM_REQUESTED else None
        self._post(event, origin or f"key {key}", confirms=confirms)

    def action_not_now(self) -> None:
        """n with no prompt on screen (the prompt was answered "not now", or is not open yet):
        decline the confirmation shown on the workflow line, if any; the controller decides."""
        self._post(Event.CONFIRM_REQUESTED, f"key {NOT_NOW_KEY}", confirms=self._shown_pending(),
                   decline=True)

    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        """Textual's binding filter: "not now" is offered (in the footer) only while a
        confirmation is on the workflow line; every other action always."""
        if action == "not_now":
            return bool(self._shown_pending())
        return True

    def _post(self, event: Event, origin: str, *, confirms: str | None = None,
              decline: bool = False) -> None:
        refused = self.session.operator.post(event, origin=origin, confirms=confirms, decline=decline)
        if refused is not None:
            self._show_results()

    def action_quit_console(self) -> None:
        """End the session: the loop aborts a procedure under way, then everything closes."""
        if not self._hil_quitting:
            self._hil_quitting = True
            self.notify("stopping: aborting any motion, closing the session…")
            self.session.operator.request_quit()

    def on_button_pressed(self, event: Button.Pressed) -> None:
        bid = event.button.id or ""
        if bid == f"cmd-{QUIT_KEY}":
            self.action_quit_console()
        elif bid.startswith("cmd-"):
            self.action_command(bid[4:], origin=f"button {bid[4:]}")

    def _on_confirm(self, transition: str, answer: Answer | None) -> None:
        """The prompt for ``transition`` closed: confirm / not now post the answer naming it,
        abort posts an abort, quit ends the session; None (closed by the console because the
        confirmation is no longer pending) posts nothing."""
        self._hil_confirm = None
        if answer is Answer.CONFIRM or answer is Answer.NOT_NOW:
            yes = answer is Answer.CONFIRM
            self._post(Event.CONFIRM_REQUESTED, "prompt confirm" if yes else "prompt not now",
                       confirms=transition, decline=not yes)
        elif answer is Answer.ABORT:
            self._post(Event.ABORT_REQUESTED, "prompt abort")
        elif answer is Answer.QUIT:
            self.action_quit_console()

    def _show_results(self) -> None:
        """Show every verdict that came back (refusals as warnings; accepted ones are visible
        as the state changes, and are listed too)."""
        for r in self.session.operator.take_results():
            self._say(r)

    def _render_messages(self) -> None:
        """The last verdicts, and how many commands still wait for the controller."""
        out = Text("\n".join(self.messages[-MESSAGES_SHOWN:]))
        queued = self.session.operator.pending_commands()
        if queued:
            out.append(("\n" if self.messages else "") + f"{queued} command(s) waiting for the controller",
                       style="bold yellow")
        self.query_one("#messages", Static).update(out)

    def _say(self, r: CommandResult) -> None:
        text = r.message()
        self.messages.append(text)
        if not r.accepted:
            self.notify(text, severity="warning")

    # ---------------------------------------------------------------- refresh
    @property
    def shown_view(self) -> ConsoleView | None:
        """The controller snapshot on screen now (None before the first): what the operator
        reads and what c / n answer. It lags the runner's latest by up to one refresh."""
        return self._hil_shown

    def refresh_view(self) -> None:
        """Show the latest snapshot (cheap; never waits on the controller). Does nothing once
        the app is shutting down: its widgets are being removed before its timers stop."""
        if not self.is_running:
            return
        runner = self.session.runner
        v = runner.latest()
        self._show_results()
        self._render_messages()
        if v is not None and v is not self._hil_shown:
            before = self._hil_shown
            self._hil_shown = v
            if before is None or before.pending != v.pending:
                self.refresh_bindings()  # "not now" is offered only while a confirmation waits
            self._render_view(v)
            self._handle_prompt(v)
        if runner.ended and self.summary is None:
            self.summary = self.session.close()
            self.exit(self.summary)

    def _handle_prompt(self, v: ConsoleView) -> None:
        if v.pending is None:
            self._hil_prompted = None
            if self._hil_confirm is not None:
                self._hil_confirm.dismiss(None)
                self._hil_confirm = None
            return
        if v.pending != self._hil_prompted and self._hil_confirm is None and not self._hil_quitting:
            self._hil_prompted = v.pending
            self._hil_confirm = ConfirmScreen(v.pending, v.pending_reason)
            name = v.pending
            self.push_screen(self._hil_confirm, lambda yes: self._on_confirm(name, yes))

    def _render_view(self, v: ConsoleView) -> None:
        banner = self.query_one("#banner", Static)
        text = banner_text(v)
        if text is None:
            banner.remove_class("shown")
        else:
            banner.update(text)
            banner.add_class("shown")
        self.query_one("#workflow", Static).update(workflow_text(v))
        self.query_one("#registration", Static).update(registration_text(v))
        self.query_one("#robot", Static).update(robot_text(v))
        self.query_one("#plan", Static).update(plan_text(v))
        self._render_markers(v)
        self.query_one("#gate", Static).update(gate_text(v))
        self.query_one("#breathing", Sparkline).data = list(v.breathing_mm)
        bar = self.query_one("#gatebar", Static)
        bar.update(gate_windows(v.breathing_mm, v.gate_tolerance_mm, max(bar.content_size.width, 1)))
        tl_widget = self.query_one("#timeline", Static)
        tl_widget.update(timeline_text(v, max(tl_widget.content_size.width, 20)))

    def _render_markers(self, v: ConsoleView) -> None:
        table = self.query_one("#markers", DataTable)
        table.border_title = markers_title(v.located_counts)
        table.clear()
        for m in v.markers:
            name = f"{m.kind} {m.index}"
            if m.position_mm is None:
                table.add_row(name, "—", "—", "—", "—", "—", Text("missing", style="bold red"))
            else:
                x, y, z = m.position_mm
                table.add_row(name, f"{x:.2f}", f"{y:.2f}", f"{z:.2f}",
                              "—" if m.residual_mm is None else f"{m.residual_mm:.3f}",
                              "—" if m.deviation_mm is None else f"{m.deviation_mm:.2f}",
                              Text("visible", style="green"))
