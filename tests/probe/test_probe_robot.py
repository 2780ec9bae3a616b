"""``hil probe`` on a UR over RTDE: the real emulator (tools/ursim) and hosts nothing answers."""

from __future__ import annotations

import contextlib
import socket
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.probe.conftest import ProbeRun, write_setup
from tests.ur_rtde.conftest import Ursim

UR_STEPS = ["host_resolves", "tcp_30004", "tcp_29999", "tcp_30003", "rtde_version", "rtde_stream",
            "dashboard", "safety_mode", "robot_mode", "remote_control", "program"]


def _robot_setup(directory: Path, host: str, controller: str = "e_series") -> Path:
    return write_setup(directory, f'[camera]\ndriver = "sim"\n\n[robot]\ndriver = "ur_rtde"\n'
                                  f'host = "{host}"\ncontroller = "{controller}"\n', sim_sections=False)


def test_e_series_emulator_all_ok(tmp_path: Path, ursim: Ursim, run_probe: Callable[..., ProbeRun]) -> None:
    run = run_probe(_robot_setup(tmp_path, ursim.host))
    checks = run.checks("robot")
    assert list(checks) == UR_STEPS
    assert all(c["status"] == "ok" for c in checks.values()), checks
    assert checks["rtde_version"]["data"]["family"] == "e_series"
    assert checks["rtde_version"]["data"]["controller_version"].startswith("5.11.")
    assert checks["rtde_stream"]["data"]["requested_hz"] == 500.0
    assert checks["safety_mode"]["message"] == "safety mode NORMAL"
    assert checks["robot_mode"]["data"] == {"robot_mode": "RUNNING"}
    assert run.device("robot")["status"] == "ok"  # (the simulated camera runs in real time: not asserted)


def test_controller_family_mismatch(tmp_path: Path, ursim: Ursim, run_probe: Callable[..., ProbeRun]) -> None:
    run = run_probe(_robot_setup(tmp_path, ursim.host, controller="cb3"))
    assert run.code == 1
    check = run.checks("robot")["rtde_version"]
    assert check["status"] == "fail"
    assert "e-Series" in check["message"]
    assert "controller = 'cb3'" in check["message"]
    assert check["hint"] == "set controller = 'e_series' in [robot] (RTDE rate 500 Hz)"
    assert list(run.checks("robot"))[-1] == "rtde_version"  # stopped at the first failure


def test_protective_stop(tmp_path: Path, ursim: Ursim, run_probe: Callable[..., ProbeRun]) -> None:
    ursim.control.protective_stop()
    run = run_probe(_robot_setup(tmp_path, ursim.host))
    assert run.code == 1
    check = run.checks("robot")["safety_mode"]
    assert check["message"] == "safety mode PROTECTIVE_STOP: the arm will not move"
    assert "unlock protective stop" in check["hint"]


def _silent_loopback() -> str:
    """A loopback address where nothing listens on the UR ports (ursim emulators use 127.100+)."""
    for last in range(3, 60):
        host = f"127.0.0.{last}"
        with contextlib.suppress(OSError), socket.socket() as s:
            s.bind((host, 30004))
            return host
    raise RuntimeError("no free loopback address")


def test_nothing_listening_fails_at_the_first_port(
    tmp_path: Path, run_probe: Callable[..., ProbeRun],
) -> None:
    host = _silent_loopback()
    run = run_probe(_robot_setup(tmp_path, host))
    assert run.code == 1
    checks = run.checks("robot")
    assert list(checks) == ["host_resolves", "tcp_30004"]
    assert checks["tcp_30004"]["message"] == f"{host}:30004 (RTDE) refuses connections"
    assert "nothing listens" in checks["tcp_30004"]["hint"]
    assert run.device("camera")["checks"][0]["name"] == "simulated"  # the other devices are still probed


@pytest.mark.parametrize("host", ["robot.invalid", "no such host"])
def test_host_that_does_not_resolve(tmp_path: Path, run_probe: Callable[..., ProbeRun], host: str) -> None:
    run = run_probe(_robot_setup(tmp_path, host), human=True)
    assert run.code == 1
    assert f"  FAIL  robot host '{host}' does not resolve" in run.out
    assert "Traceback" not in run.out + run.err


def test_emergency_stop(tmp_path: Path, ursim: Ursim, run_probe: Callable[..., ProbeRun]) -> None:
    ursim.control.estop()
    run = run_probe(_robot_setup(tmp_path, ursim.host))
    check = run.checks("robot")["safety_mode"]
    assert check["message"] == "safety mode ROBOT_EMERGENCY_STOP: the arm will not move"
    assert check["hint"].startswith("release the emergency-stop button")


def test_ports_open_but_nothing_speaks_rtde(tmp_path: Path, run_probe: Callable[..., ProbeRun]) -> None:
    """A host that accepts TCP on the UR ports but never answers (a proxy, another service): the
    probe fails at the RTDE handshake after its timeout instead of hanging."""
    host = _silent_loopback()
    with contextlib.ExitStack() as stack:
        for port in (30004, 29999, 30003):
            srv = stack.enter_context(socket.socket())
            srv.bind((host, port))
            srv.listen(4)  # connections complete in the backlog; nobody ever reads or writes
        run = run_probe(_robot_setup(tmp_path, host))
    checks = run.checks("robot")
    assert [c["status"] for c in checks.values()] == ["ok", "ok", "ok", "ok", "fail"]
    assert checks["rtde_version"]["message"] == (
        f"RTDE on {host}:30004 does not answer the protocol: silent for 2 s")


def test_connect_timeout_is_one_plain_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                           run_probe: Callable[..., ProbeRun]) -> None:
    from drivers.ur_rtde import probe_wire

    def times_out(host: str, port: int, timeout_s: float) -> float:
        raise TimeoutError("timed out")

    monkeypatch.setattr(probe_wire, "tcp_connect", times_out)
    run = run_probe(_robot_setup(tmp_path, "127.0.0.1"))
    check = run.checks("robot")["tcp_30004"]
    assert check["message"] == "no answer from 127.0.0.1:30004 (RTDE) within 2 s"
    assert "ping it" in check["hint"]
