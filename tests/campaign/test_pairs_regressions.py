"""Regressions found by the compound-fault campaign (``hil campaign --pairs``, seed 1).

``frozen_frame+motion_rejected@compensate`` (and ``stale_timestamp+motion_rejected@compensate``):
the recording robot counted two servo steps as
acceleration violations that reached the driver. Both were refused by the driver (motion rejected)
and never moved the arm; the recorder had kept the velocity of the refused step and the pose of the
last accepted one, while the servo loop restarts its stream from the actual pose at rest after a
failed command. The recorder now does the same.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces.errors import DeviceFaultError
from drivers.interfaces.robot import MotionLimits, Robot, RobotMode, RobotState, SafetyStatus
from hil.campaign.pairs import select_pairs
from hil.campaign.pairs_campaign import pair_spec
from hil.campaign.recorder import RecordingRobot
from hil.campaign.runner import RunSpec, run_one
from hil.clock import ManualClock
from hil.config import default_setup_path
from hil.geometry.transform import RigidTransform

PERIOD_S = 0.008


class _RejectingRobot(Robot):
    """Accepts every servo step (huge limits of its own) unless ``rejecting``; reports rest at 0."""

    def __init__(self) -> None:
        super().__init__("robot", MotionLimits((-1e9,) * 3, (1e9,) * 3, 1e9, 1e9, 1e9),
                         T_flange_from_tcp=RigidTransform.identity())
        self.clock = ManualClock()
        self.rejecting = False
        self.executed: list[float] = []

    @property
    def control_rate_hz(self) -> float:
        return 125.0

    def _open(self) -> None: ...

    def _close(self) -> None: ...

    def _move_linear(self, T: RigidTransform, speed: float, accel: float, blocking: bool) -> None: ...

    def _servo(self, T: RigidTransform, period_s: float) -> None:
        if self.rejecting:
            raise DeviceFaultError(self.name, "motion command rejected")
        self.executed.append(float(T.t[0]))

    def _stop(self, decel: float) -> None: ...

    def _state_now(self) -> RobotState:
        return RobotState(t_ns=self.clock.now_ns(), q_rad=np.zeros(6),
                          T_robot_from_tcp=RigidTransform.identity(), tcp_speed_mm_s=0.0,
                          mode=RobotMode.IDLE, safety=SafetyStatus.NORMAL)


def _stream(reject_third: bool) -> list[tuple[str, ...]]:
    """Servo steps at x = 0.01, 0.03, 0.15 (refused when ``reject_third``), 0.0 mm, 8 ms apart,
    checked against 2000 mm/s^2: the last step reverses the refused one's 15 mm/s."""
    inner = _RejectingRobot()
    rec = RecordingRobot(inner, MotionLimits((-100.0,) * 3, (100.0,) * 3, 50.0, 2000.0, 1.0), inner.clock)
    rec.open()
    for x in (0.01, 0.03, 0.15, 0.0):
        rec.state_now()
        inner.rejecting = reject_third and x == 0.15
        if inner.rejecting:
            with pytest.raises(DeviceFaultError):
                rec.servo(RigidTransform(np.eye(3), np.array([x, 0.0, 0.0])), PERIOD_S)
        else:
            rec.servo(RigidTransform(np.eye(3), np.array([x, 0.0, 0.0])), PERIOD_S)
        inner.clock.advance(PERIOD_S)
    assert inner.executed == ([0.01, 0.03, 0.0] if reject_third else [0.01, 0.03, 0.15, 0.0])
    return [c.violations for c in rec.recording.commands]


def test_a_step_after_a_refused_one_is_checked_from_rest_at_the_reported_pose() -> None:
    # before the fix: from 0.03 mm (the last accepted) with the refused step's 15 mm/s, the
    # return to 0.0 read as -3.75 mm/s: "servo step acceleration: 2344 mm/s^2"
    assert _stream(reject_third=True) == [(), (), (), ()]


def test_the_same_reversal_without_a_refusal_is_a_violation() -> None:
    """The check still sees a reversal the arm would have made (this test can fail)."""
    got = _stream(reject_third=False)
    assert got[:3] == [(), (), ()]
    assert got[3] == ("servo step acceleration: 4219 mm/s^2",)  # 15 -> -18.75 mm/s in 8 ms


@pytest.mark.slow
@pytest.mark.parametrize(("name", "outcome"), [
    # a rejected servo command faults the controller (tests/servo/test_client_errors.py): both
    # reach a safe state and recover to lock
    ("frozen_frame+motion_rejected@compensate", "safe_state"),
    ("stale_timestamp+motion_rejected@compensate", "safe_state"),
])
def test_motion_rejected_with_a_camera_fault_while_compensating_passes(name: str, outcome: str,
                                                                       tmp_path: Path) -> None:
    """The campaign runs that found it (seed 1), placed in the baseline's COMPENSATE window
    [6.9633, 7.4193] s (it moves with the procedure's timing: update it from a baseline run's
    ``state_windows_s`` when APPROACH or GATE change): no command outside the limits reached the
    driver."""
    (sc,) = select_pairs([name])
    spec = pair_spec(sc, 1, {"compensate": [6.9633, 7.4193]}, None, str(default_setup_path()), None, 90.0)
    assert isinstance(spec, RunSpec)
    assert (spec.start_s, spec.second_start_s) == (7.1001, 7.1501)
    out = run_one(replace(spec, log_dir=str(tmp_path)))
    assert (out.limit_violations, out.reasons) == ([], [])
    assert (out.outcome, out.final_state, out.passed) == (outcome, "done", True)
    assert out.state_at_onset == "compensate"
