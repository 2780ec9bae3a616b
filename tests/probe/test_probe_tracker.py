"""``hil probe`` on serial trackers: the real emulator (tools/trackersim) on a pseudo-terminal."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from tests.probe.conftest import ProbeRun, TrackerSim, write_setup

FOB_FAST = "reset_hold_s = 0.0\nreset_settle_s = 0.0\nauto_config_wait_s = 0.1\n"


def _fob(directory: Path, port: str, baud: int, sensors: str = "{ reference = 1, needle = 2 }") -> Path:
    return write_setup(directory, f'[tracker]\ndriver = "fob"\nport = "{port}"\nbaud_rate = {baud}\n'
                                  f"sensors = {sensors}\n{FOB_FAST}")


def _aurora(directory: Path, port: str, sensors: str = '{ reference = "0A", needle = "0B" }') -> Path:
    return write_setup(directory, f'[tracker]\ndriver = "aurora"\nport = "{port}"\nbaud_rate = 115200\n'
                                  f"sensors = {sensors}\nbreak_as_nul = true\nreset_timeout_s = 1.0\n")


def test_flock_all_ok(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                      run_probe: Callable[..., ProbeRun]) -> None:
    sim = trackersim("--protocol", "fob", "--birds", "2", "--baud", "38400", "--motion", "static")
    run = run_probe(_fob(tmp_path, sim.path, 38400))
    checks = run.checks("tracker")
    assert list(checks) == ["port_exists", "port_permissions", "port_opens", "baud_rate", "identity",
                            "flock_status", "driver_builds", "driver_opens", "streams",
                            "sensor_reference", "sensor_needle"]
    assert all(c["status"] == "ok" for c in checks.values()), checks
    assert checks["identity"]["data"]["model"] == "6DFOB"
    assert checks["flock_status"]["data"]["sensors"] == {"reference": "address 1: present (6DFOB)",
                                                        "needle": "address 2: present (6DFOB)"}
    assert checks["sensor_needle"]["data"]["records"] > 0
    assert run.device("tracker")["status"] == "ok"


def test_flock_wrong_baud_says_where_it_answers(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                                                run_probe: Callable[..., ProbeRun]) -> None:
    sim = trackersim("--protocol", "fob", "--baud", "38400", "--motion", "static")
    run = run_probe(_fob(tmp_path, sim.path, 115200, "{ reference = 0 }"))
    assert run.code == 1
    check = run.checks("tracker")["baud_rate"]
    assert check["status"] == "fail"
    assert check["message"] == ("no valid answer at the configured 115200 baud; the Bird (6DFOB) answers "
                                "at 38400 baud")
    assert check["hint"].startswith("set baud_rate = 38400 in [tracker]")
    assert check["data"] == {"configured_baud": 115200, "answers_at_baud": 38400, "model": "6DFOB"}


def test_flock_bird_missing_from_the_bus(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                                         run_probe: Callable[..., ProbeRun]) -> None:
    sim = trackersim("--protocol", "fob", "--birds", "2", "--motion", "static")
    run = run_probe(_fob(tmp_path, sim.path, 115200, "{ reference = 1, needle = 3 }"))
    check = run.checks("tracker")["flock_status"]
    assert check["status"] == "fail"
    assert check["message"] == "flock status: 'needle' (FBB address 3) not on the bus"


def test_aurora_all_ok(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                       run_probe: Callable[..., ProbeRun]) -> None:
    sim = trackersim("--protocol", "aurora", "--tools", "2", "--motion", "static")
    run = run_probe(_aurora(tmp_path, sim.path))
    checks = run.checks("tracker")
    assert list(checks) == ["port_exists", "port_permissions", "port_opens", "reset", "identity", "baud_rate",
                            "tools", "driver_builds", "driver_opens", "streams", "sensor_reference",
                            "sensor_needle"]
    assert all(c["status"] == "ok" for c in checks.values()), checks
    assert checks["identity"]["message"] == ("identity: NDI AURORA Control Firmware / "
                                             "Freeze Tag: AURORA Rev 008")
    assert checks["tools"]["data"] == {"handles": ["0A", "0B"]}
    assert checks["sensor_needle"]["data"]["position_mm"] == [40.0, 0.0, -250.0]
    assert run.device("tracker")["status"] == "ok"


def test_aurora_wrong_baud_says_where_it_answers(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                                                 run_probe: Callable[..., ProbeRun]) -> None:
    sim = trackersim("--protocol", "aurora", "--fault", "wrong_baud,baud=57600", "--motion", "static")
    run = run_probe(_aurora(tmp_path, sim.path))
    assert run.code == 1
    check = run.checks("tracker")["reset"]
    assert check["status"] == "fail"
    assert check["message"].startswith("no RESET after a serial break, but the Aurora answers at 57600 baud")
    assert check["data"] == {"answers_at_baud": 57600}


def test_aurora_tool_not_plugged_in(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                                    run_probe: Callable[..., ProbeRun]) -> None:
    sim = trackersim("--protocol", "aurora", "--tools", "1", "--motion", "static")
    run = run_probe(_aurora(tmp_path, sim.path))
    check = run.checks("tracker")["tools"]
    assert check["status"] == "fail"
    assert check["message"] == "no tool on 'needle' (port handle 0B); the Aurora has handles 0A"


def test_serial_port_that_does_not_exist(tmp_path: Path, run_probe: Callable[..., ProbeRun]) -> None:
    port = str(tmp_path / "ttyUSB7")
    run = run_probe(_fob(tmp_path, port, 115200), human=True)
    assert run.code == 1
    assert f"  FAIL  serial port {port} does not exist" in run.out.splitlines()
    assert "Traceback" not in run.out + run.err


def test_serial_port_that_is_not_a_device(tmp_path: Path, run_probe: Callable[..., ProbeRun]) -> None:
    port = tmp_path / "not-a-tty"
    port.write_text("")
    run = run_probe(_fob(tmp_path, str(port), 115200))
    check = run.checks("tracker")["port_exists"]
    assert check["message"] == f"{port} exists but is a file, not a serial device"


def test_silent_device_on_an_existing_port(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                                           run_probe: Callable[..., ProbeRun]) -> None:
    sim = trackersim("--protocol", "fob", "--fault", "silence", "--motion", "static")
    run = run_probe(_fob(tmp_path, sim.path, 115200, "{ reference = 0 }"))
    check = run.checks("tracker")["baud_rate"]
    assert check["status"] == "fail"
    assert check["message"].startswith(
        "no answer to EXAMINE VALUE (model id) at 115200 baud nor at any other standard rate")


def test_aurora_sensor_out_of_volume_and_missing(tmp_path: Path, trackersim: Callable[..., TrackerSim],
                                                 run_probe: Callable[..., ProbeRun]) -> None:
    script = tmp_path / "poses.csv"
    script.write_text("t_s,sensor,x_mm,y_mm,z_mm,qw,qx,qy,qz\n"
                      "0,0A,0,0,-900,1,0,0,0\n"
                      "0,0B,,,,,,,\n", encoding="utf-8")
    sim = trackersim("--protocol", "aurora", "--poses", str(script), "--motion", "static")
    run = run_probe(_aurora(tmp_path, sim.path))
    checks = run.checks("tracker")
    assert checks["sensor_reference"]["status"] == "warn"
    assert checks["sensor_reference"]["message"].startswith("sensor 'reference': out of the field volume")
    assert "out_of_volume" in checks["sensor_reference"]["data"]["flags"]
    assert checks["sensor_needle"]["status"] == "warn"
    assert checks["sensor_needle"]["message"].startswith("sensor 'needle': missing")
    assert run.device("tracker")["status"] == "warn"  # the tracker works; the sensors need moving / plugging


def test_serial_port_without_permission(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                        trackersim: Callable[..., TrackerSim],
                                        run_probe: Callable[..., ProbeRun]) -> None:
    import hil.probe.serial_port as serial_port

    sim = trackersim("--protocol", "fob", "--motion", "static")
    monkeypatch.setattr(serial_port.os, "access", lambda path, mode: False)  # we run as root here
    run = run_probe(_fob(tmp_path, sim.path, 115200, "{ reference = 0 }"))
    check = run.checks("tracker")["port_permissions"]
    assert check["status"] == "fail"
    assert check["message"].startswith(f"no read/write permission on {sim.path} (crw")
    assert "dialout" in check["hint"]
