"""``hil states``: print the procedure's transition table (text) or its diagram (mermaid, dot)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from hil.controller.config import ProcedureConfig
from hil.controller.fsm import TRANSITIONS, render_dot, render_markdown, render_mermaid, render_text


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "states", help="print the procedure state machine (table or diagram)",
        description="Print the complete transition table (every state x event: transition, "
                    "in-state handling or rejection) or a diagram of the transitions.")
    p.add_argument("--format", choices=["text", "mermaid", "dot", "markdown"], default="text",
                   help="text: the whole table; mermaid/dot: diagram of the transitions; "
                        "markdown: docs/states.md")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    confirm = ProcedureConfig().confirm
    render = {"text": render_text, "mermaid": render_mermaid, "dot": render_dot,
              "markdown": render_markdown}[args.format]
    sys.stdout.write(render(TRANSITIONS, confirm))
    return 0
