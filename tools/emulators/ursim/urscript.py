"""A tiny URScript subset for programs other than ur-rtde's ``rtde_control`` script.

Enough for ``sendCustomScript`` / ``sendCustomScriptFunction`` and one-line programs a user sends to
port 30003: ``movel``, ``movej``, ``stopl``, ``stopj``, ``sleep``, ``write_output_integer_register``
and ``write_output_float_register`` with literal arguments. Everything else (``textmsg``,
``set_*``, ``popup``, comments, control flow) is skipped; a skipped line is reported in the events.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_CALL = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*\((.*)\)\s*$")
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_KWARG = re.compile(rf"([A-Za-z_]+)\s*=\s*({_NUM})")
_VECTOR = re.compile(r"(p?)\[([^\]]*)\]")
_SUM = re.compile(rf"^\s*({_NUM})\s*(?:\+\s*({_NUM}))?\s*$")

MOVEL_DEFAULTS = {"a": 1.2, "v": 0.25}
MOVEJ_DEFAULTS = {"a": 1.4, "v": 1.05}


class ScriptSyntaxError(ValueError):
    """A statement of the supported subset has arguments that are not literals."""


@dataclass(frozen=True)
class Statement:
    """One executable statement: ``op`` in movel, movej, stopl, stopj, sleep, write_int, write_float,
    skip; ``values`` the vector or scalar arguments; ``kwargs`` a, v, t, r."""

    op: str
    values: tuple[float, ...] = ()
    is_pose: bool = False
    kwargs: tuple[tuple[str, float], ...] = ()
    text: str = ""

    def kw(self, name: str, default: float) -> float:
        return dict(self.kwargs).get(name, default)


def _sum(expr: str) -> float:
    m = _SUM.match(expr)
    if m is None:
        raise ScriptSyntaxError(f"not a literal: {expr.strip()!r}")
    return float(m.group(1)) + (float(m.group(2)) if m.group(2) else 0.0)


def parse_statement(line: str) -> Statement:
    text = line.split("#", 1)[0].strip()
    if not text or text.startswith(("def ", "end", "global ", "sec ")):
        return Statement("skip", text=text)
    m = _CALL.match(text)
    if m is None:
        return Statement("skip", text=text)
    name, args = m.group(1), m.group(2)
    if name in ("movel", "movej"):
        vec = _VECTOR.search(args)
        if vec is None:
            raise ScriptSyntaxError(f"{name}: target is not a literal vector: {text!r}")
        values = tuple(float(x) for x in vec.group(2).split(","))
        if len(values) != 6:
            raise ScriptSyntaxError(f"{name}: target needs 6 values: {text!r}")
        rest = args[vec.end():]
        kwargs = tuple((k, float(v)) for k, v in _KWARG.findall(rest))
        return Statement(name, values, vec.group(1) == "p", kwargs, text)
    if name in ("stopl", "stopj", "sleep"):
        first = args.split(",")[0]
        return Statement(name, (_sum(first),), text=text)
    if name in ("write_output_integer_register", "write_output_float_register"):
        parts = args.rsplit(",", 1)
        if len(parts) != 2:
            raise ScriptSyntaxError(f"{name}: needs (index, value): {text!r}")
        op = "write_int" if "integer" in name else "write_float"
        return Statement(op, (_sum(parts[0]), _sum(parts[1])), text=text)
    return Statement("skip", text=text)


def parse_program_body(text: str) -> list[Statement]:
    """Statements of a ``def name(): ... end`` program or of bare lines, in order."""
    return [parse_statement(line) for line in text.splitlines()]
