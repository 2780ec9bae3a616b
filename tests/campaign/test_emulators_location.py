"""Where the campaign finds the emulators it starts: ``$HIL_EMULATORS_DIR``, an importable
``emulators`` package, or the source checkout's ``tools/`` -- and, when none holds them (a
non-editable install), one plain line saying how to get them, before any process is started."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Any

import pytest

from hil.campaign import emulators
from hil.campaign.emulators import ENV_EMULATORS_DIR, EmulatorsMissingError, emulators_dir, start_ursim
from hil.campaign.transport import run_transport_campaign, select_transport

CHECKOUT_TOOLS = Path(__file__).resolve().parents[2] / "tools"


@pytest.fixture
def installed_without_checkout(monkeypatch: pytest.MonkeyPatch) -> None:
    """As in a non-editable install: no variable, no importable ``emulators``, no checkout."""
    monkeypatch.delenv(ENV_EMULATORS_DIR, raising=False)
    real_find_spec = importlib.util.find_spec

    def find_spec(name: str, *args: Any) -> Any:
        return None if name == "emulators" else real_find_spec(name, *args)

    monkeypatch.setattr(emulators.importlib.util, "find_spec", find_spec)
    monkeypatch.setattr(emulators, "_checkout_tools", lambda: None)


def test_the_checkout_is_found_from_a_source_tree(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_EMULATORS_DIR, raising=False)
    assert emulators._checkout_tools() == CHECKOUT_TOOLS
    assert emulators_dir() == CHECKOUT_TOOLS


def test_the_variable_comes_first(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    package = tmp_path / "emulators"
    package.mkdir()
    (package / "__init__.py").write_text("")
    monkeypatch.setenv(ENV_EMULATORS_DIR, str(tmp_path))
    assert emulators_dir() == tmp_path.resolve()


def test_a_variable_without_emulators_is_one_plain_line(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
) -> None:
    monkeypatch.setenv(ENV_EMULATORS_DIR, str(tmp_path))
    with pytest.raises(EmulatorsMissingError) as err:
        emulators_dir()
    assert str(err.value) == (f"{ENV_EMULATORS_DIR}={tmp_path} holds no emulators package "
                              "(emulators/__init__.py): point it at a checkout's tools/ directory")


@pytest.mark.usefixtures("installed_without_checkout")
def test_missing_emulators_say_how_to_get_them_in_one_line(tmp_path: Path) -> None:
    why = ("the device emulators (the emulators package in tools/ of the source checkout) are not "
           f"installed with hil: set {ENV_EMULATORS_DIR} to a checkout's tools/ directory")
    with pytest.raises(EmulatorsMissingError) as err:
        emulators_dir()
    assert str(err.value) == why
    with pytest.raises(EmulatorsMissingError):
        start_ursim(tmp_path)  # before any process or address is taken
    assert list(tmp_path.iterdir()) == []


@pytest.mark.usefixtures("installed_without_checkout")
def test_a_transport_campaign_without_emulators_fails_each_run_with_that_line(tmp_path: Path) -> None:
    said: list[str] = []
    summary = run_transport_campaign(select_transport(["rtde_estop@register", "serial_silence@lock"]), [1],
                                     out_dir=tmp_path, progress=said.append)
    assert (summary["runs"], summary["failed"]) == (2, 2)
    reasons = {r["scenario"]: r["reasons"] for r in summary["results"]}
    assert reasons == {s: ["emulator: the device emulators (the emulators package in tools/ of the source "
                           f"checkout) are not installed with hil: set {ENV_EMULATORS_DIR} to a checkout's "
                           "tools/ directory"] for s in ("rtde_estop@register", "serial_silence@lock")}
    assert said[0].startswith("rtde_estop@register_s1: FAIL emulator did not start (the device emulators")
    assert json.loads((tmp_path / "transport.json").read_text())["failed"] == 2
