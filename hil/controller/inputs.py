"""What one control tick works from, frozen: read once at the start of the tick, so every part of
the tick (supervision, perception, the phase) sees the same instant."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.interfaces.camera import StereoFrame
from drivers.interfaces.robot import RobotState
from drivers.interfaces.tracker import TrackerSample
from hil.controller.operator_input import OperatorCommand

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TickInputs:
    """One tick's inputs.

    Attributes:
        t_ns: the controller clock when the devices had been read.
        command: the operator command taken this tick (None: none).
        frame: the stereo pair (exposure time ``frame.left.t_ns``).
        points_mm: the marker centres located in it (optical frame, mm, any order), or None when
            they are located by the tick itself.
        robot: the robot state read this tick.
        tracker: the tracker's latest samples by sensor name (empty without a tracker).
    """

    t_ns: int
    command: OperatorCommand | None
    frame: StereoFrame
    points_mm: FloatArray | None
    robot: RobotState
    tracker: dict[str, TrackerSample]
