"""No path accepts a robot-moving command unless the setup enables it: the robot moves only through
the controller's safety layer, and every motion command outside the configured limits is refused
before it reaches a driver."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces.errors import LimitViolationError
from drivers.interfaces.robot import MotionLimits
from hil.clock import ManualClock
from hil.config import build_devices, load_setup
from hil.geometry.transform import RigidTransform

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def robot():  # type: ignore[no-untyped-def]
    setup = load_setup(ROOT / "configs" / "sim.toml")
    devices = build_devices(setup, ManualClock(1_000_000_000))
    devices.open_all()
    yield devices.robot, setup.safety.motion_limits()
    devices.close_all()


def test_sim_robot_refuses_a_move_outside_the_workspace(robot) -> None:  # type: ignore[no-untyped-def]
    r, limits = robot
    assert isinstance(limits, MotionLimits)
    here = r.state_now().T_robot_from_tcp
    outside = RigidTransform(here.R, np.array(limits.workspace_max_mm) + 10.0)
    with pytest.raises(LimitViolationError):
        r.move_linear(outside, speed_mm_s=10.0, accel_mm_s2=100.0)


def test_sim_robot_refuses_excess_speed(robot) -> None:  # type: ignore[no-untyped-def]
    r, limits = robot
    here = r.state_now().T_robot_from_tcp
    with pytest.raises(LimitViolationError):
        r.move_linear(here, speed_mm_s=limits.max_speed_mm_s * 2, accel_mm_s2=100.0)


def test_no_network_listener_imports_the_robot_interface() -> None:
    """No in-process listener (today: OpenIGTLink) can command motion over the network: no module
    that binds or listens on a socket imports the Robot interface."""
    import ast

    for path in (ROOT / "hil").rglob("*.py"):
        src = path.read_text()
        if not any(k in src for k in (".bind(", ".listen(", "start_server", "socketserver")):
            continue  # not a listener (clients such as hil/probe connect out, read-only)
        tree = ast.parse(src)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "drivers.interfaces.robot":
                pytest.fail(f"{path.relative_to(ROOT)} opens sockets and imports the robot interface")
