"""Shared hypothesis strategies and helpers for the fuzz suite.

The contract every parser is held to: a correct parse, or a typed error (a
:class:`hil.errors.HilError`, or the protocol layer's own decode error) with a message; never
another exception, a hang, or a silently wrong value.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any, TypeVar

from hypothesis import strategies as st

T = TypeVar("T")
E = TypeVar("E", bound=BaseException)

#: JSON scalars, including the non-standard tokens Python's json accepts (NaN, Infinity).
json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)

#: Small JSON documents of any shape.
json_values = st.recursive(
    json_scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=5), st.dictionaries(st.text(max_size=8), children, max_size=5)
    ),
    max_leaves=20,
)


def paths_of(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every path (tuple of keys / indices) into a JSON document, the root included."""
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += paths_of(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += paths_of(v, (*prefix, i))
    return out


def replace_at(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    """A copy of ``doc`` with the node at ``path`` replaced (deleted when value is _DELETE)."""
    if not path:
        return value
    copy = json.loads(json.dumps(doc))
    node = copy
    for key in path[:-1]:
        node = node[key]
    if value is DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return copy


DELETE = object()


@st.composite
def mutated_json(draw: st.DrawFn, doc: Any) -> Any:
    """``doc`` with 1-3 nodes replaced by random JSON or deleted."""
    out = doc
    for _ in range(draw(st.integers(1, 3))):
        paths = paths_of(out)
        path = draw(st.sampled_from(paths))
        value = draw(st.one_of(json_values, st.just(DELETE))) if path else draw(json_values)
        out = replace_at(out, path, value)
    return out


@st.composite
def mutated_bytes(draw: st.DrawFn, data: bytes, max_edits: int = 4) -> bytes:
    """``data`` with 1..max_edits byte edits (flip, replace, insert, delete, truncate)."""
    buf = bytearray(data)
    for _ in range(draw(st.integers(1, max_edits))):
        op = draw(st.sampled_from(["flip", "replace", "insert", "delete", "truncate"]))
        i = draw(st.integers(0, max(len(buf) - 1, 0)))
        if op == "flip" and buf:
            buf[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "replace" and buf:
            buf[i] = draw(st.integers(0, 255))
        elif op == "insert":
            buf[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete" and buf:
            del buf[i : i + draw(st.integers(1, 8))]
        elif op == "truncate":
            del buf[i:]
    return bytes(buf)


def require_message(exc: BaseException) -> None:
    """A typed error must say what is wrong."""
    if not str(exc).strip():
        raise AssertionError(f"{type(exc).__name__} raised without a message")


def outcome(fn: Callable[[], T], allowed: tuple[type[E], ...]) -> T | E:
    """Run ``fn``: its result, or the allowed typed error it raised (any other exception escapes,
    which fails the test with the traceback). The typed error must carry a message."""
    try:
        return fn()
    except allowed as exc:
        require_message(exc)
        return exc


def all_finite(values: Any) -> bool:
    if isinstance(values, int | float):
        return math.isfinite(values)
    return all(all_finite(v) for v in values)
