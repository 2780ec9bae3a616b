"""A synthetic session log written with the real SessionLog writer and the controller's event
names (hil/controller/events.py, hil/safety/layer.py), with known values."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hil.clock import ManualClock
from hil.geometry.transform import RigidTransform
from hil.session.log import SessionLog

FRE_MM = 0.4321
TRE_MM = 0.8765
ROBOT_FRE_MM = 0.2109
LOCK_ERROR_MM = 0.3456
FAULT_REASON = "camera: no frame for 0.30 s"
#: compensation pairs (index -> reason) the surrogate target model fell back on
TARGET_FALLBACKS = {3: "markers off the pattern by 2.40 mm > 2.00 mm",
                    4: "markers off the pattern by 2.40 mm > 2.00 mm",
                    11: "the seen markers carry 20% of the 4D CT's breathing pattern (need 25%)"}
#: compensation pairs (index -> which) the model steered held at a bound
TARGET_HELD = {15: "breathing beyond the 4D CT's range: score 30.0 mm (CT 0.0..16.0 mm), target held at "
                   "24.0 mm",
               16: "the model's turn 11.0 deg held at the bound 10.0 deg"}
REFERENCE_MM = np.array([[0.0, 0.0, 1000.0], [80.0, 0.0, 1000.0], [0.0, 80.0, 1010.0],
                         [80.0, 80.0, 990.0], [40.0, 40.0, 1020.0]])
DT_S = 0.1


class _Writer:
    def __init__(self, log: SessionLog, clock: ManualClock) -> None:
        self.log, self.clock = log, clock

    def enter(self, source: str, state: str, transition: str) -> None:
        self.log.write("transition_applied", source=source, target=state, input="x", reason="",
                       transition=transition)
        self.log.write("state_entered", state=state, reason="", transition=transition)

    def tick(self) -> None:
        self.clock.advance(DT_S)


def write_full_session(path: Path) -> Path:
    """IDLE -> REGISTER -> PLAN -> APPROACH -> GATE -> COMPENSATE -> LOCK -> FAULT -> APPROACH
    ... -> LOCK -> DONE, with breathing, guide errors, truth, commands, live markers."""
    clock = ManualClock()
    log = SessionLog(path, clock, header={"setup": "simulator", "config_sha256": "ab" * 32,
                                          "gate_tolerance_mm": 1.5, "lock_tolerance_mm": 0.5})
    w = _Writer(log, clock)
    w.tick()
    log.write("operator_command", input="start_requested")
    w.enter("idle", "register", "start")
    for _ in range(10):
        w.tick()
    log.write("registration_done", fre_mm=FRE_MM, tre_expected_mm=TRE_MM, markers=5, frames=10,
              T_optical_from_image=RigidTransform.identity(), robot_fre_mm=ROBOT_FRE_MM,
              T_robot_from_optical=RigidTransform.identity(), reference_optical_mm=REFERENCE_MM,
              residuals_mm=[0.3, 0.5, 0.4, 0.45, 0.5])
    w.enter("register", "plan", "register_to_plan")
    w.tick()
    w.enter("plan", "approach", "plan_to_approach")
    for k in range(20):
        w.tick()
        log.write("command_sent", command="move_linear", target=RigidTransform.identity(),
                  speed_mm_s=50.0, accel_mm_s2=200.0)
        log.write("robot_state", tcp_speed_mm_s=50.0 * math.sin(math.pi * k / 19))
    log.write("approach_measured", guide_error_mm=0.21, correction=0, T_bias=RigidTransform.identity())
    w.enter("approach", "gate", "approach_to_gate")
    for k in range(30):
        w.tick()
        dev = 3.0 * abs(math.cos(2 * math.pi * k / 30)) + 0.2
        is_open = k >= 24
        log.write("gate_measured", deviation_rms_mm=dev, markers=5, dwell_s=0.0, open=is_open,
                  shape_mm=0.1 * k, marker_deviations_mm=[dev, dev, None, dev, dev + 0.2])
        live = REFERENCE_MM + np.array([0.0, 0.0, dev])
        live[4] += [0.0, 0.2, 0.0]
        log.write("markers_measured", live_mm=live)
        if is_open:
            break
    w.enter("gate", "compensate", "gate_to_compensate")
    for k in range(20):
        w.tick()
        log.write("compensation_step", exposure_t_ns=clock.now_ns(), latency_detect_ms=30.0,
                  latency_command_ms=35.0, change_mm=1.0, predicted_s=0.05, command_mm=[0.0, 0.0, 0.0],
                  guide_error_mm=2.0 / (k + 1), gate_deviation_mm=0.4, change_fre_mm=0.05 * k,
                  target_score_mm=0.3 * k, target_shift_mm=0.2 * k,
                  target_turn_deg=0.0 if k in TARGET_FALLBACKS else 1.5 * math.sin(2 * math.pi * k / 20),
                  target_fallback=TARGET_FALLBACKS.get(k, ""), target_limited=TARGET_HELD.get(k, ""))
        log.write("command_sent", command="servo", target_mm=[0.0, 0.0, 0.0], period_s=DT_S, speed_mm_s=5.0)
        log.write("truth_error", state="compensate", position_mm=1.0 + 0.1 * k, direction_deg=0.5)
    w.enter("compensate", "lock", "compensate_to_lock")
    w.tick()
    log.write("lock_measured", guide_error_mm=LOCK_ERROR_MM, gate_deviation_mm=0.3, shape_mm=0.25,
              marker_deviations_mm=[0.3, 0.3, 0.3, 0.3, 0.5])
    log.write("truth_error", state="lock", position_mm=0.61, direction_deg=0.7)
    w.tick()
    log.write("fault_detected", reason=FAULT_REASON, state="lock")
    w.enter("lock", "fault", "fault")
    w.tick()
    w.tick()
    w.enter("fault", "approach", "recover")
    w.tick()
    w.enter("approach", "lock", "compensate_to_lock")
    w.tick()
    log.write("lock_measured", guide_error_mm=0.4, gate_deviation_mm=0.3)
    log.write("truth_error", state="lock", position_mm=0.52, direction_deg=0.4)
    w.tick()
    w.enter("lock", "done", "lock_to_done")
    log.close(final_state="done")
    return path


def write_empty_session(path: Path) -> Path:
    """A session that started and closed with nothing in between."""
    clock = ManualClock()
    log = SessionLog(path, clock)
    clock.advance(1.0)
    log.close()
    return path
