"""The console's key vocabulary, in one place: the command keys (footer, buttons, bindings),
the keys a confirmation dialog takes, and the sentence the workflow line shows while a
confirmation waits. Every place that names a key to the operator reads it from here, so what the
screen says to press is what acts.
"""

from __future__ import annotations

from hil.controller.fsm import Event

#: key -> (operator event, label). The console posts nothing else.
COMMANDS: dict[str, tuple[Event, str]] = {
    "s": (Event.START_REQUESTED, "Start"),
    "c": (Event.CONFIRM_REQUESTED, "Confirm"),
    "p": (Event.PAUSE_REQUESTED, "Pause"),
    "r": (Event.RESUME_REQUESTED, "Resume"),
    "t": (Event.RETRACT_REQUESTED, "Retract"),
    "a": (Event.ABORT_REQUESTED, "Abort"),
    "x": (Event.RESET_REQUESTED, "Reset"),
}
QUIT_KEY = "q"
CONFIRM_KEY = "c"
ABORT_KEY = "a"
#: declines a confirmation for now: it stays pending (confirm later, or abort)
NOT_NOW_KEY = "n"
NOT_NOW_LABEL = "Not now"

#: The keys a confirmation dialog takes: key -> label. Any other key pressed on the dialog is
#: answered on the dialog with :func:`not_taken_text`.
DIALOG_KEYS: dict[str, str] = {
    CONFIRM_KEY: COMMANDS[CONFIRM_KEY][1],
    NOT_NOW_KEY: NOT_NOW_LABEL,
    ABORT_KEY: COMMANDS[ABORT_KEY][1],
    QUIT_KEY: "Quit",
}

#: What the workflow line says while a confirmation waits (the dialog's keys, in its words).
CONFIRM_KEYS_TEXT = (f"press {CONFIRM_KEY} (confirm), {NOT_NOW_KEY} (not now) "
                     f"or {ABORT_KEY} (abort)")


def not_taken_text(key: str) -> str:
    """What the dialog says when ``key`` (a textual key name, e.g. ``"y"``, ``"p"``) is pressed
    on it and is not one of :data:`DIALOG_KEYS`."""
    if key in COMMANDS:
        what = f"{key} ({COMMANDS[key][1]}) is not taken while a confirmation is open"
    else:
        what = f"{key} is not a key of this dialog"
    return f"{what}: {CONFIRM_KEYS_TEXT}"
