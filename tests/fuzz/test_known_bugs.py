"""Reproducers of defects the fuzz suite found in other areas' parsers (one test each).

Every defect found so far is fixed, so each test here is now a plain regression test. A newly
found defect goes in as ``xfail(strict=True)`` with the exception it raises and a reason naming
the owner and the fix (see ``_json_params``); when the owner fixes it the test XPASSes, which
fails the run under ``strict``, and the marker is deleted.
"""

from __future__ import annotations

import asyncio
import struct
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.config import load_setup
from hil.controller.plan_file import load_plan
from hil.errors import HilError
from hil.io.points import read_points
from hil.session.log import VerifyReport, read_session_log, verify_session_log
from hil.vision.camera_model import load_calibration

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))

DEEP_JSON = "[" * 100_000  # json.loads -> RecursionError
HUGE_INT = "1" * 5000  # json/tomllib -> ValueError (int max str digits, 4300)
JSON_FIX = (
    "catch (ValueError, RecursionError) around json.loads (JSONDecodeError is a ValueError) and "
    "raise the loader's typed error"
)


def _read_all(path: Path) -> Any:
    return list(read_session_log(path))


JSON_LOADERS: list[tuple[str, Callable[[Path], Any], str]] = [
    ("plan", load_plan, ".json"),
    ("points_json", read_points, ".json"),
    ("points_mrk", read_points, ".mrk.json"),
    ("session_verify", verify_session_log, ".jsonl"),
    ("session_read", _read_all, ".jsonl"),
]
# hil/io/points.py, hil/controller/plan_file.py, hil/session/log.py: fixed, plain regression tests
FIXED_JSON_LOADERS = ("points_json", "points_mrk", "plan", "session_verify", "session_read")


def _json_params(raises: type[Exception], reason: str) -> list[Any]:
    """JSON_LOADERS as params: the fixed loaders plain, the others strict-xfail."""
    xfail = pytest.mark.xfail(strict=True, raises=raises, reason=reason)
    return [
        pytest.param(name, loader, suffix, id=name, marks=() if name in FIXED_JSON_LOADERS else xfail)
        for name, loader, suffix in JSON_LOADERS
    ]


@pytest.mark.parametrize(
    ("name", "loader", "suffix"),
    _json_params(
        RecursionError, "owners of hil/controller/plan_file.py, hil/session/log.py: " + JSON_FIX
    ),
)
def test_deeply_nested_json_is_a_typed_error(
    tmp_path: Path, name: str, loader: Callable[[Path], Any], suffix: str
) -> None:
    p = tmp_path / f"deep{suffix}"
    p.write_text(DEEP_JSON + "\n")
    if name == "session_verify":  # its contract: a failed report naming the line, never an exception
        rep = loader(p)
        assert isinstance(rep, VerifyReport)
        assert (rep.ok, rep.first_bad_line) == (False, 1)
        assert "nested too deeply" in rep.reason
        return
    with pytest.raises(HilError, match="nested too deeply"):
        loader(p)


@pytest.mark.parametrize(("name", "loader", "suffix"), _json_params(ValueError, "same owners: " + JSON_FIX))
def test_huge_integer_literal_is_a_typed_error(
    tmp_path: Path, name: str, loader: Callable[[Path], Any], suffix: str
) -> None:
    p = tmp_path / f"big{suffix}"
    p.write_text(HUGE_INT + "\n")
    if name == "session_verify":  # its contract: a failed report naming the line, never an exception
        rep = loader(p)
        assert isinstance(rep, VerifyReport)
        assert (rep.ok, rep.first_bad_line) == (False, 1)
        assert "unusable JSON" in rep.reason
        return
    with pytest.raises(HilError):
        loader(p)


@pytest.mark.parametrize("text", ["a = " + "[" * 100_000, "a = " + HUGE_INT], ids=["deep", "huge_int"])
def test_hostile_toml_is_a_config_error(tmp_path: Path, text: str) -> None:
    p = tmp_path / "hostile.toml"
    p.write_text(text)
    with pytest.raises(HilError, match="unusable TOML"):
        load_setup(p)


@pytest.mark.parametrize("which", ["plan", "calibration"])  # plan: as_points raises GeometryError
def test_integer_too_large_for_float_is_a_typed_error(tmp_path: Path, which: str) -> None:
    import json

    if which == "plan":
        doc = json.loads((ROOT / "configs/plans/sim_plan.json").read_text())
        doc["entry_mm"] = [10**400, 0, 0]
        loader: Callable[[Path], Any] = load_plan
    else:
        doc = json.loads((ROOT / "configs/calibration/sim_stereo.json").read_text())
        doc["left"]["K"][0][0] = 10**400
        loader = load_calibration
    p = tmp_path / f"{which}.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(HilError):
        loader(p)


@pytest.mark.parametrize("key", ["camera_frame_max_age_ms", "robot_state_max_age_ms", "tracker_max_age_ms"])
def test_infinite_watchdog_age_is_refused(tmp_path: Path, key: str) -> None:
    import shutil

    shutil.copytree(ROOT / "configs/calibration", tmp_path / "calibration")
    lines = [
        f"{key} = inf" if ln.startswith(f"{key} =") else ln
        for ln in (ROOT / "configs/sim.toml").read_text().splitlines()
    ]
    p = tmp_path / "inf.toml"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(HilError, match=key):
        load_setup(p)


# ----------------------------------------------------------------------------- UR emulator
def _serve(stream: bytes) -> Any:
    from tests.fuzz.test_rtde_emulator import _serve as serve

    return asyncio.run(serve(stream))


def test_ursim_denormal_output_frequency() -> None:
    """A denormal output frequency is treated like 0 (stream at the controller's rate)."""
    from emulators.ursim import protocol as proto

    setup = proto.pack(proto.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 5e-324) + b"timestamp")
    _, writer = _serve(setup)
    assert bytes(writer.sent) == proto.pack(proto.CONTROL_PACKAGE_SETUP_OUTPUTS, b"\x01DOUBLE")


def test_ursim_more_than_255_input_recipes() -> None:
    """Recipe ids 1..255 are granted; the 256th setup is a protocol violation (connection closed)."""
    from emulators.ursim import protocol as proto

    one = proto.pack(proto.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_24")
    _, writer = _serve(one * 256)
    expected = b"".join(proto.pack(proto.CONTROL_PACKAGE_SETUP_INPUTS, bytes([rid]) + b"INT32")
                        for rid in range(1, 256))
    assert bytes(writer.sent) == expected
    assert writer.closed


@pytest.mark.parametrize("cmd", [11, 24, 1, 3])
def test_ursim_nan_register_faults_the_program_instead_of_raising(cmd: int) -> None:
    from emulators.ursim.controller import ControllerVersion, RuntimeState, UrController

    c = UrController(ControllerVersion.parse("5.11"))
    c.power_on()
    c.brake_release()
    c.load_program("def rtde_control():\n  rtde_cmd()\nend\n")
    c.set_inputs(
        {"input_int_register_0": cmd, **{f"input_double_register_{i}": float("nan") for i in range(12)}}
    )
    for _ in range(10):
        c.tick()
    assert np.all(np.isfinite(c.q))
    assert c.runtime_state is not RuntimeState.PLAYING


def test_aurora_parse_command_without_name() -> None:
    from drivers.tracker_serial import aurora_protocol as ap

    with pytest.raises(ap.NdiDecodeError):
        ap.parse_command(b" ")


@pytest.mark.parametrize("reader", ["read_session_log", "load_session"])
def test_non_utf8_session_log_is_a_typed_error(tmp_path: Path, reader: str) -> None:
    from hil.report.session_data import load_session
    from tests.fuzz.session_fixture import write_session

    p = write_session(tmp_path / "s.jsonl")
    raw = bytearray(p.read_bytes())
    raw[0] = 0xFB
    p.write_bytes(bytes(raw))
    read = _read_all if reader == "read_session_log" else load_session
    with pytest.raises(HilError, match="line 1: not UTF-8"):
        read(p)


def test_infinite_fault_start_is_refused(tmp_path: Path) -> None:
    import shutil

    shutil.copytree(ROOT / "configs/calibration", tmp_path / "calibration")
    text = (ROOT / "configs/sim_faults.toml").read_text().replace("start_s = 2.0", "start_s = inf", 1)
    p = tmp_path / "inf_fault.toml"
    p.write_text(text)
    with pytest.raises(HilError, match="start_s"):
        load_setup(p)
