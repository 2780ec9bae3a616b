"""Config of the UR3 / UR3e driver over RTDE (``[robot] driver = "ur_rtde"``).

A leaf of its package: it imports no driver module; the factory lives in
:mod:`drivers.ur_rtde.plugin`.

Example::

    [robot]
    driver = "ur_rtde"
    host = "192.168.56.10"          # the controller (or 127.0.0.1 for tools/ursim)
    controller = "cb3"              # "cb3": UR3, RTDE at 125 Hz; "e_series": UR3e, 500 Hz
    servo_lookahead_time_s = 0.05
    servo_gain = 500
    rtde_watchdog_min_hz = 5.0      # the controller stops the program if we go silent for 200 ms

Units: seconds, hertz, millimetres; the driver converts to UR's metres and axis-angle itself.

Servo parameters (``servo_lookahead_time_s``, ``servo_gain``), chosen deliberately:
    UR's servoj smooths the target stream over the lookahead time; the ur-rtde examples' 0.1 s
    (gain 300) costs ~30 ms of tracking lag, a third of a breathing-compensation error budget at
    20 mm/s of skin motion. The controller here already rate-limits and step-checks every servo
    target (MotionLimits.check_step), so less smoothing is needed on the arm: 0.05 s halves the
    lag (~15 ms) while keeping enough filtering that camera-rate (30 Hz) target steps do not excite
    the arm; gain 500 (UR's range 100-2000) tightens tracking without the vibration the maximum
    gains give with quantised targets. 0.03 s (UR's minimum) is allowed for a stiffer loop.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, model_validator

from drivers.ur_rtde.wire import CONTROLLER_RATE_HZ
from hil.config.types import STRICT, TransformConfig


class UrRtdeRobotConfig(BaseModel):
    """``[robot] driver = "ur_rtde"``: a UR3 (CB3) or UR3e (e-Series) through the ur-rtde library.

    Attributes:
        host: controller address (IPv4 or name).
        controller: ``cb3`` (PolyScope 3.x, RTDE 125 Hz) or ``e_series`` (PolyScope 5.x, 500 Hz); the
            driver checks it against the version the controller reports.
        frequency_hz: RTDE rate override (default: the controller's rate above).
        servo_lookahead_time_s, servo_gain: servoL smoothing and gain (see the module doc).
        connect_timeout_s: each TCP probe / dashboard connect; the ur-rtde constructors themselves
            cannot be interrupted (they hold the GIL), so the driver probes the ports first.
        ready_timeout_s: waits for the control script to run, a protective stop to clear, the arm to
            power on during recovery.
        move_timeout_margin_s: a blocking move may take its profile time x 1.5 plus this margin
            before the driver stops it and raises DeviceTimeoutError.
        state_max_age_s: ``state_now`` raises DeviceTimeoutError when the controller timestamp has
            not advanced for this long (a stalled stream).
        rtde_watchdog_min_hz: arm the controller's RTDE input watchdog at this minimum rate (the
            driver kicks it at 3x); 0 leaves it off. The driver arms it lower when its window
            would not outlast a blocking stop (1.5 x (max speed / max acceleration + 50 ms)):
            the kicker cannot run while the library waits for a stop to complete.
        reconnect_attempts, reconnect_backoff_s: how ``recover()`` rebuilds lost interfaces.
        T_flange_from_tcp: the tool (needle guide) offset; the controller's own TCP stays at the
            flange and the driver applies this offset on the host.
    """

    model_config = STRICT

    driver: Literal["ur_rtde"]
    host: str = Field(min_length=1)
    controller: Literal["cb3", "e_series"] = "cb3"
    frequency_hz: float | None = Field(None, gt=0, le=500)
    servo_lookahead_time_s: float = Field(0.05, ge=0.03, le=0.2)
    servo_gain: float = Field(500.0, ge=100, le=2000)
    connect_timeout_s: float = Field(3.0, gt=0, le=60)
    ready_timeout_s: float = Field(8.0, gt=0, le=120)
    move_timeout_margin_s: float = Field(5.0, ge=0, le=600)
    state_max_age_s: float = Field(0.25, gt=0, le=10)
    rtde_watchdog_min_hz: float = Field(5.0, ge=0, le=100)
    reconnect_attempts: int = Field(3, ge=1, le=100)
    reconnect_backoff_s: float = Field(1.0, ge=0, le=60)
    T_flange_from_tcp: TransformConfig = Field(default_factory=TransformConfig.identity)

    @model_validator(mode="after")
    def _rate_fits_controller(self) -> UrRtdeRobotConfig:
        if self.frequency_hz is not None and self.frequency_hz > CONTROLLER_RATE_HZ[self.controller]:
            raise ValueError(
                f"frequency_hz {self.frequency_hz} exceeds the {self.controller} RTDE rate "
                f"{CONTROLLER_RATE_HZ[self.controller]:g} Hz")
        return self

    @property
    def rate_hz(self) -> float:
        return self.frequency_hz if self.frequency_hz is not None else CONTROLLER_RATE_HZ[self.controller]


#: The name plugins.builtin looks up.
UrRtdeConfig = UrRtdeRobotConfig
