"""The camera's cross-check of the robot's reported pose (docs/safety.md, "Camera cross-check").

The servo loop compares the commands with the pose the arm *reports* (hil/safety/following.py).
This check closes the chain on the camera's side: in every frame where the flange markers are
seen, the TCP pose the camera measures (``C = T_robot_from_optical @ O``, robot frame, through the
robot registration) is compared with the pose the robot reported at the frame's exposure time
(``E``). Their ratio is the bias measurement ``D = E @ C^-1`` of seed 001 §2.3; APPROACH converges
the closed-loop bias ``T_bias`` onto it, so afterwards the robot's report is predicted from the
camera as ``T_bias @ C``. The discrepancy is ``(T_bias @ C)^-1 @ E``, expressed at the TCP (so a
small rotation error is not magnified by the distance to the robot base): its translation in mm
and its angle in degrees. When it
stays farther than ``max_mm`` (or turned more than ``max_deg``) for ``max_s`` or longer, the arm is
not where the robot says it is relative to the camera — an encoder or report fault, a slipped
flange marker plate, a bumped camera or robot base — and the procedure must not go on guiding a
needle on that data: the controller faults with the figures.

Active in GATE, COMPENSATE and LOCK (the bias is converged by then; in LOCK the bias stays fixed,
so the check also holds the locked pose against the camera). A frame without enough flange markers
neither confirms nor clears a divergence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.interfaces.camera import StereoFrame
from hil.controller.estimate import Estimate
from hil.controller.fsm import State

#: States in which the check runs (the bias was converged by APPROACH).
CHECKED_STATES = frozenset({State.GATE, State.COMPENSATE, State.LOCK})


@dataclass(frozen=True)
class CrossCheckBounds:
    """``[safety] camera_discrepancy_*``: translation (mm), rotation (degrees), how long (s)."""

    max_mm: float = 2.0
    max_deg: float = 2.0
    max_s: float = 0.3


class CameraCrossCheck:
    """Compares camera-measured and robot-reported TCP poses frame by frame (module doc)."""

    def __init__(self, bounds: CrossCheckBounds) -> None:
        self.bounds = bounds
        self._beyond_since_ns: int | None = None
        self._max_mm = 0.0
        self._max_deg = 0.0
        #: the latest discrepancy measured (mm, degrees), for the frame log; None before one
        self.last: tuple[float, float] | None = None

    def reset(self) -> None:
        self._beyond_since_ns = None
        self.last = None

    def check(self, est: Estimate, frame: StereoFrame, state: State) -> str | None:
        """The fault reason when the discrepancy has lasted ``max_s`` (the timer then restarts),
        else None. Never raises; a frame it cannot judge (state, markers, history) returns None."""
        if state not in CHECKED_STATES:
            self.reset()
            return None
        O_opt = est.T_optical_from_tcp_measured()
        E = est.robot_pose_at(frame.left.t_ns)
        if O_opt is None or E is None or est.robot_reg is None:
            return None
        R = (est.T_bias @ est.robot_reg.T_robot_from_optical @ O_opt).inverse() @ E
        err_mm = float(math.sqrt(float(R.t @ R.t)))
        cos = (float(R.R[0, 0] + R.R[1, 1] + R.R[2, 2]) - 1.0) * 0.5
        err_deg = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
        self.last = (err_mm, err_deg)
        b = self.bounds
        if err_mm <= b.max_mm and err_deg <= b.max_deg:
            self._beyond_since_ns = None
            return None
        t = frame.left.t_ns
        if self._beyond_since_ns is None:
            self._beyond_since_ns, self._max_mm, self._max_deg = t, err_mm, err_deg
        self._max_mm, self._max_deg = max(self._max_mm, err_mm), max(self._max_deg, err_deg)
        held_s = (t - self._beyond_since_ns) * 1e-9
        if held_s < b.max_s:
            return None
        self._beyond_since_ns = None
        return (f"camera cross-check: the TCP the camera measures is {err_mm:.2f} mm / {err_deg:.2f} deg "
                f"from where the robot reports it, for {held_s * 1e3:.0f} ms (max {self._max_mm:.2f} mm / "
                f"{self._max_deg:.2f} deg; bound {b.max_mm:g} mm / {b.max_deg:g} deg for "
                f"{b.max_s * 1e3:.0f} ms)")
