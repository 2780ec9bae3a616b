"""A plain ur-rtde user script (no project driver) drives the emulator like a UR3."""

from __future__ import annotations

import pytest
import rtde_control
import rtde_receive

from hil.geometry.transform import RigidTransform
from tests.ur_rtde.conftest import Ursim, wait_for

pytestmark = pytest.mark.emulator


def _rotation(pose: list[float]) -> RigidTransform:
    return RigidTransform.from_rotvec(pose[3:], [1000.0 * x for x in pose[:3]])


def test_plain_ur_rtde_script_moves_50_mm_and_reads_the_tcp_back(
    ursim: Ursim, capfd: pytest.CaptureFixture[str]
) -> None:
    rtde_r = rtde_receive.RTDEReceiveInterface(ursim.host)
    rtde_c = rtde_control.RTDEControlInterface(ursim.host)
    try:
        assert rtde_c.isProgramRunning()
        pose = rtde_r.getActualTCPPose()
        target = list(pose)
        target[2] += 0.050
        assert rtde_c.moveL(target, 0.1, 0.5)
        # the receive connection may trail the control connection by one package: read the next one
        ts = rtde_r.getTimestamp()
        wait_for(lambda: rtde_r.getTimestamp() > ts, what="next state package")
        new_pose = rtde_r.getActualTCPPose()
        assert new_pose[:3] == pytest.approx(target[:3], abs=1e-9)
        # rotation vectors near pi come back with either sign (trap 7): compare rotations
        assert _rotation(new_pose).is_close(_rotation(target), atol_mm=1e-9, atol_rad=1e-9)
        fk = rtde_c.getForwardKinematics()
        assert _rotation(fk).is_close(_rotation(target), atol_mm=1e-6, atol_rad=1e-9)
        q = rtde_r.getActualQ()
        assert rtde_c.getInverseKinematics(new_pose) == pytest.approx(q, abs=1e-9)
        rtde_c.stopScript()
        assert not rtde_c.isProgramRunning()
    finally:
        rtde_c.disconnect()
        rtde_r.disconnect()
    capfd.readouterr()  # the C++ client prints to the process's stdout/stderr


def test_custom_script_function_runs_and_the_control_script_comes_back(
    ursim: Ursim, capfd: pytest.CaptureFixture[str]
) -> None:
    rtde_r = rtde_receive.RTDEReceiveInterface(ursim.host)
    rtde_c = rtde_control.RTDEControlInterface(ursim.host)
    try:
        pose = rtde_r.getActualTCPPose()
        target = list(pose)
        target[0] += 0.030
        body = "movel(p[{}], a=0.5, v=0.1)\nsleep(0.05)".format(",".join(repr(x) for x in target))
        assert rtde_c.sendCustomScriptFunction("nudge", body)
        assert rtde_c.isProgramRunning()  # rtde_control was re-uploaded
        ts = rtde_r.getTimestamp()
        wait_for(lambda: rtde_r.getTimestamp() > ts, what="next state package")
        assert rtde_r.getActualTCPPose()[:3] == pytest.approx(target[:3], abs=1e-9)
        assert rtde_c.moveL(pose, 0.1, 0.5)  # and it still takes commands
    finally:
        rtde_c.stopScript()
        rtde_c.disconnect()
        rtde_r.disconnect()
    capfd.readouterr()


def test_a_bare_urscript_line_on_port_30003_moves_the_arm(ursim: Ursim) -> None:
    import socket

    start = ursim.control.status()["tcp_pose"]
    target = list(start)
    target[2] += 0.02
    line = "movel(p[{}], a=1.2, v=0.25)\n".format(",".join(repr(x) for x in target))
    with socket.create_connection((ursim.host, 30003), timeout=2.0) as s:
        s.sendall(line.encode())
        wait_for(lambda: ursim.control.status()["runtime_state"] == "STOPPED"
                 and abs(ursim.control.status()["tcp_pose"][2] - target[2]) < 1e-9, what="line executed")
