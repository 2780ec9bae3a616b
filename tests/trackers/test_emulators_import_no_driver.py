"""No emulator imports a driver: each one speaks its device's protocol with its own encoder, so the
driver's codec is checked against something other than itself (the issue: "with one codec on both
ends a framing bug passes every test")."""

from __future__ import annotations

import ast
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[2] / "tools"
EMULATORS = TOOLS / "emulators"


def driver_imports(path: Path) -> list[str]:
    """``line: module`` of every import of the ``drivers`` package in ``path`` (at any depth,
    lazy imports included)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module is not None:
            names = [node.module]
        found += [f"{node.lineno}: {name}" for name in names
                  if name == "drivers" or name.startswith("drivers.")]
    return found


def test_no_module_under_tools_emulators_imports_a_driver() -> None:
    modules = sorted(EMULATORS.rglob("*.py"))
    assert len(modules) > 20  # the scan sees the emulators (trackersim, ursim, fakegv)
    offenders = {str(p.relative_to(TOOLS)): driver_imports(p) for p in modules}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_scan_sees_every_import_form(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    src.write_text("import drivers.tracker_serial.aurora_protocol as ap\n"
                   "from drivers.tracker_serial import fob_protocol\n"
                   "import driverslib\n"
                   "def f():\n    from drivers import faults\n    import drivers\n"
                   "from . import drivers_local\n", encoding="utf-8")
    assert driver_imports(src) == ["1: drivers.tracker_serial.aurora_protocol",
                                   "2: drivers.tracker_serial", "5: drivers", "6: drivers"]
