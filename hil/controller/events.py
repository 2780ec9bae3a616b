"""The session-log event names the controller writes, as constants (docs/run.md lists the fields).

One name, one meaning: reports, the campaign judge and the console read these records, so a name
is never spelt inline. State-machine records (``transition_*``) are named by
:data:`FIRE_RECORD` from the fire result's kind.
"""

from __future__ import annotations

from typing import Final

# operator
OPERATOR_COMMAND: Final = "operator_command"
OPERATOR_COMMAND_RESULT: Final = "operator_command_result"
START_REFUSED: Final = "start_refused"
RUN_TIME_EXCEEDED: Final = "run_time_exceeded"
CONSOLE_LOOP_FAILED: Final = "console_loop_failed"
# state machine
STATE_ENTERED: Final = "state_entered"
FIRE_RECORD: Final = {"transition": "transition_applied", "rejected": "transition_rejected",
                      "pending": "transition_pending", "stay": "event_handled"}
# supervision
FAULT_DETECTED: Final = "fault_detected"
STOP_FAILED: Final = "stop_failed"
STOP_DELIVERED: Final = "stop_delivered"
ROBOT_RECOVER_ATTEMPTED: Final = "robot_recover_attempted"
OBSERVER_FAILED: Final = "observer_failed"
# camera pipeline
PIPELINE_PRIMED: Final = "pipeline_primed"
PIPELINE_PRIME_FAILED: Final = "pipeline_prime_failed"
FRAME_PREFETCH_STOPPED: Final = "frame_prefetch_stopped"
FRAME_MEASURED: Final = "frame_measured"
# phases
BREATH_HOLD_REQUESTED: Final = "breath_hold_requested"
REGISTRATION_FAILED: Final = "registration_failed"
REGISTRATION_DONE: Final = "registration_done"
REFERENCE_SENSOR_RECORDED: Final = "reference_sensor_recorded"
PLAN_REFUSED: Final = "plan_refused"
PLAN_ACCEPTED: Final = "plan_accepted"
APPROACH_MEASURED: Final = "approach_measured"
GATE_MEASURED: Final = "gate_measured"
GATE_TIMED_OUT: Final = "gate_timed_out"
#: the gate's checks held but too little of the requested breath-hold was left (once per hold)
GATE_HOLD_TOO_SHORT: Final = "gate_hold_too_short"
CORRECTION_OUT_OF_BOUNDS: Final = "correction_out_of_bounds"
COMPENSATION_STEP: Final = "compensation_step"
#: the loop's predictor fell back (innovation beyond its bound, a gap, a wrong rate, a non-finite
#: output): alpha-beta sets the setpoint until it is warm again (docs/prediction.md "In the loop")
PREDICTOR_FALLBACK: Final = "predictor_fallback"
SERVO_DEADLINE_MISSED: Final = "servo_deadline_missed"
#: the servo loop's counters, once per second of controller time (hil/servo/figures.py); the loop's
#: own events (servo_stop_delivered, servo_refused, ...) are named in hil/servo/loop.py
SERVO_STATS: Final = "servo_stats"
#: the following-error supervision in force (hil/safety/following.py): lag, bounds, their source
SERVO_FOLLOWING_BOUNDS: Final = "servo_following_bounds"
LOCK_MEASURED: Final = "lock_measured"
DRIFT_ALARM: Final = "drift_alarm"
# needle and tracker
NEEDLE_AXIS_MEASURED: Final = "needle_axis_measured"
NEEDLE_AXIS_UNAVAILABLE: Final = "needle_axis_unavailable"
NEEDLE_AXIS_ALARM: Final = "needle_axis_alarm"
NEEDLE_CHECK_REFUSED: Final = "needle_check_refused"
NEEDLE_TRACKED: Final = "needle_tracked"
REFERENCE_IN_USE: Final = "reference_in_use"
REFERENCE_RELEASED: Final = "reference_released"
REFERENCE_DISAGREEMENT: Final = "reference_disagreement"
REFERENCE_AGREES: Final = "reference_agrees"
#: the path points at the target sensor's target again / no longer (hil/controller/target_sensor.py)
TARGET_SENSOR_IN_USE: Final = "target_sensor_in_use"
TARGET_SENSOR_LOST: Final = "target_sensor_lost"
# simulator truth (an observer, never the control path)
TRUTH_ERROR: Final = "truth_error"
