"""What a phase asks of the robot, as values: the controller executes them, in order, through the
safety layer (every motion command is checked there), after the phase's step and before its events
are processed.

- :class:`MoveLinear`: a linear move to a TCP pose (robot frame) at a speed and acceleration.
- :class:`Track`: a tracking setpoint for the servo loop (COMPENSATE, once per pair).
- :class:`Hold`: the servo loop brings the arm to rest from its current command and holds that
  pose, commanding it every period (LOCK: the arm stays under servo control and supervision).
- :class:`Stop`: stop the arm; a stop that cannot be delivered is retried every tick until it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.robot import RobotState
from hil.geometry.transform import RigidTransform


@dataclass(frozen=True)
class MoveLinear:
    target: RigidTransform   # T_robot_from_tcp, mm
    speed_mm_s: float
    accel_mm_s2: float


@dataclass(frozen=True)
class Track:
    """A tracking setpoint (see :class:`hil.servo.shm.Setpoint`): the TCP pose ``T_robot_from_tcp``
    (mm) at ``t_ref_ns`` and its velocity (mm/s, rad/s; robot frame); valid until
    ``valid_until_ns`` (controller clock). ``robot_state``: the state the setpoint was made with,
    checked by the safety layer for age and safety instead of reading another (None: it reads)."""

    setpoint: RigidTransform
    v_mm_s: NDArray[np.float64]
    w_rad_s: NDArray[np.float64]
    t_ref_ns: int
    valid_until_ns: int
    exposure_t_ns: int
    frame_seq: int
    speed_scale: float
    max_horizon_s: float
    lead_s: float
    robot_state: RobotState | None = None


@dataclass(frozen=True)
class Hold:
    reason: str = ""


@dataclass(frozen=True)
class Stop:
    reason: str


Command = MoveLinear | Track | Hold | Stop
