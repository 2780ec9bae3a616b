"""What a phase asks of the robot, as values: the controller executes them, in order, through the
safety layer (every motion command is checked there), after the phase's step and before its events
are processed.

- :class:`MoveLinear`: a linear move to a TCP pose (robot frame) at a speed and acceleration.
- :class:`Track`: one servo set-point (robot frame) held for ``dt_s`` (COMPENSATE's stream).
- :class:`Hold`: nothing new: keep the last command (the robot holds or finishes its move).
- :class:`Stop`: stop the arm; a stop that cannot be delivered is retried every tick until it is.
"""

from __future__ import annotations

from dataclasses import dataclass

from hil.geometry.transform import RigidTransform


@dataclass(frozen=True)
class MoveLinear:
    target: RigidTransform   # T_robot_from_tcp, mm
    speed_mm_s: float
    accel_mm_s2: float


@dataclass(frozen=True)
class Track:
    setpoint: RigidTransform  # T_robot_from_tcp, mm
    dt_s: float


@dataclass(frozen=True)
class Hold:
    reason: str = ""


@dataclass(frozen=True)
class Stop:
    reason: str


Command = MoveLinear | Track | Hold | Stop
