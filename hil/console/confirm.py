"""The confirmation dialog: shown while the controller waits for the operator to confirm a
transition that moves the robot or ends the procedure.

It takes exactly the keys of :data:`hil.console.keys.DIALOG_KEYS` (c confirm, n not now, a abort,
q quit — the same keys the workflow line and the dialog's own footer and buttons name) and
answers every other key on the dialog itself, saying why it did nothing. It never posts a
command: it dismisses with an :class:`Answer` and the app posts it.
"""

from __future__ import annotations

import enum
from typing import ClassVar

from rich.text import Text
from textual import events
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Footer, Label
from textual.widgets.button import ButtonVariant

from hil.console.keys import ABORT_KEY, CONFIRM_KEY, DIALOG_KEYS, NOT_NOW_KEY, QUIT_KEY, not_taken_text

#: What confirming each transition does, for the prompt.
CONFIRM_TEXT: dict[str, str] = {
    "register_to_plan": "Accept the registration and plan the guide pose.",
    "plan_to_approach": "The robot will MOVE to the stand-off pose above the entry.",
    "approach_to_gate": "Start waiting for the hold-breath gate.",
    "gate_to_compensate": "The robot will FOLLOW the patient to the corrected entry.",
    "compensate_to_lock": "Stop and hold the guide at the corrected entry.",
    "lock_to_done": "Finish the procedure (the robot stays stopped).",
    # a recovery re-asking a confirmation that was pending (never given) when the procedure stopped
    "recover": "The robot will RECOVER and MOVE to the stand-off pose above the entry.",
    "resume": "The robot will MOVE to the stand-off pose above the entry.",
}


class Answer(enum.Enum):
    """How the operator closed the dialog."""

    CONFIRM = "confirm"
    NOT_NOW = "not_now"  # the confirmation stays pending
    ABORT = "abort"      # abort the procedure (safe stop)
    QUIT = "quit"        # end the console session (it aborts a procedure under way)


_KEY_ANSWER: dict[str, Answer] = {CONFIRM_KEY: Answer.CONFIRM, NOT_NOW_KEY: Answer.NOT_NOW,
                                  ABORT_KEY: Answer.ABORT, QUIT_KEY: Answer.QUIT}
_BUTTON_VARIANT: dict[Answer, ButtonVariant] = {Answer.CONFIRM: "success", Answer.NOT_NOW: "default",
                                                 Answer.ABORT: "error"}


class ConfirmScreen(ModalScreen[Answer | None]):
    """Asks the operator to confirm a pending transition. Dismissed with the :class:`Answer`, or
    with None when the console closes it because the confirmation is no longer pending."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding(key, f"answer('{_KEY_ANSWER[key].value}')", label) for key, label in DIALOG_KEYS.items()]
    DEFAULT_CSS = """
    ConfirmScreen { align: center middle; }
    #confirm-box { width: 72; height: auto; border: thick $warning; background: $surface; padding: 1 2; }
    #confirm-box Label { width: 100%; margin-bottom: 1; }
    #confirm-box #confirm-said { color: $warning; text-style: bold; }
    #confirm-box Horizontal { height: auto; align: center middle; }
    #confirm-box Button { margin: 0 1; }
    """

    def __init__(self, transition: str, reason: str) -> None:
        super().__init__()
        self.transition_name = transition
        self.hint_text = CONFIRM_TEXT.get(transition, "") + (f" ({reason})" if reason else "")
        #: what the dialog said about the last key it did not take ("" until one is pressed)
        self.said = ""

    def compose(self) -> ComposeResult:
        with Vertical(id="confirm-box"):
            yield Label(Text(f"Confirm {self.transition_name}?", style="bold"))
            yield Label(Text(self.hint_text))
            yield Label("", id="confirm-said")
            with Horizontal():
                for answer, variant in _BUTTON_VARIANT.items():
                    key = next(k for k, a in _KEY_ANSWER.items() if a is answer)
                    yield Button(f"{DIALOG_KEYS[key]} ({key})", id=f"answer-{answer.value}",
                                 variant=variant)
        yield Footer()

    def action_answer(self, answer: str) -> None:
        self.dismiss(Answer(answer))

    def on_button_pressed(self, event: Button.Pressed) -> None:
        event.stop()
        self.dismiss(Answer((event.button.id or "").removeprefix("answer-")))

    def on_key(self, event: events.Key) -> None:
        """A key no binding of the dialog (or of its focused button) takes: say so on the dialog
        and keep it open. Keys that are bound pass on to their binding."""
        if event.key in self.active_bindings:
            return
        event.stop()
        event.prevent_default()
        self.said = not_taken_text(event.key)
        self.query_one("#confirm-said", Label).update(Text(self.said))
