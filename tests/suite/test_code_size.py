"""Size rule of the core (issue 15): no class in ``hil/`` over 400 lines, no function over 80.

Lengths are counted as Python's ast reports them: from the ``def`` / ``class`` line to the last
line of the body (decorators excluded), i.e. ``end_lineno - lineno + 1``. Methods and nested
functions are functions too.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
MAX_CLASS_LINES = 400
MAX_FUNCTION_LINES = 80


def oversized(root: Path) -> list[str]:
    """Every class over MAX_CLASS_LINES and function over MAX_FUNCTION_LINES under ``root``, as
    ``path:line kind name (N lines > limit)`` (path relative to ``root``'s parent), in file and
    line order."""
    found: list[tuple[str, int, str]] = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).as_posix()
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                kind, limit = "class", MAX_CLASS_LINES
            elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                kind, limit = "function", MAX_FUNCTION_LINES
            else:
                continue
            assert node.end_lineno is not None
            lines = node.end_lineno - node.lineno + 1
            if lines > limit:
                found.append((rel, node.lineno, f"{kind} {node.name} ({lines} lines > {limit})"))
    return [f"{rel}:{line} {what}" for rel, line, what in sorted(found)]


def test_no_oversized_class_or_function_in_hil() -> None:
    found = oversized(REPO / "hil")
    assert not found, "split these into smaller units with one job each:\n" + "\n".join(found)


def _lines(indent: int, n: int) -> str:
    return "".join(" " * indent + f"x{i} = {i}\n" for i in range(n))


def test_the_check_names_what_is_too_long(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "ok.py").write_text(f"class Fine:\n{_lines(4, 399)}\n\ndef fine() -> None:\n{_lines(4, 79)}")
    (pkg / "sub" / "mod.py").write_text(
        "import functools\n"  # line 1
        "@functools.cache\n"  # decorators are not counted
        f"def at_limit() -> None:\n{_lines(4, 79)}"  # lines 3-82: 80 lines, allowed
        f"async def too_long() -> None:\n{_lines(4, 80)}"  # lines 83-163: 81 lines
        f"class Big:\n{_lines(4, 400)}"  # lines 164-564: 401 lines
        "class Small:\n"  # line 565, 83 lines: a small class
        "    def outer(self) -> None:\n"  # line 566, 82 lines
        f"        def inner() -> None:\n{_lines(12, 80)}"  # line 567, 81 lines
    )
    assert oversized(pkg) == [
        "pkg/sub/mod.py:83 function too_long (81 lines > 80)",
        "pkg/sub/mod.py:164 class Big (401 lines > 400)",
        "pkg/sub/mod.py:566 function outer (82 lines > 80)",
        "pkg/sub/mod.py:567 function inner (81 lines > 80)",
    ]
