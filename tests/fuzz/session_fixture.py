"""A small but realistic session log written by :class:`hil.session.log.SessionLog`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hil.clock import ManualClock
from hil.geometry.transform import RigidTransform
from hil.session.log import SessionLog

STATES = ["register", "plan", "approach", "gate", "compensate", "lock", "done"]


def write_session(path: Path, steps: int = 6) -> Path:
    """A closed session: start record, transitions, measurements, a fault, close. Returns ``path``."""
    clock = ManualClock(1_000_000_000)
    log = SessionLog(path, clock, {"setup": "sim.toml", "config_sha256": "0" * 64})
    prev = "idle"
    for s in STATES:
        clock.advance(0.5)
        log.write(
            "transition_applied",
            source=prev,
            target=s,
            input="test",
            reason="fixture",
            transition=f"{prev}_to_{s}",
        )
        log.write("state_entered", state=s, reason="fixture", transition=f"{prev}_to_{s}")
        prev = s
        for k in range(steps):
            clock.advance(1 / 15)
            if s == "compensate":
                log.write(
                    "compensation_step",
                    exposure_t_ns=clock.now_ns() - 30_000_000,
                    latency_detect_ms=12.0,
                    latency_command_ms=30.0,
                    change_mm=0.4 * k,
                    predicted_s=0.05,
                    command_mm=np.array([1.0, 2.0, 3.0 + k]),
                    guide_error_mm=0.2,
                    gate_deviation_mm=0.1,
                )
                log.write("truth_error", state=s, position_mm=0.1, direction_deg=0.05)
            elif s == "gate":
                log.write("gate_measured", deviation_rms_mm=0.3, markers=6, dwell_s=0.1 * k, open=k > 3)
        if s == "approach":
            log.write("fault_detected", reason="camera: injected", state=s)
            log.write(
                "registration_done",
                fre_mm=0.02,
                tre_expected_mm=0.2,
                markers=6,
                frames=5,
                T_optical_from_image=RigidTransform.identity(),
                robot_fre_mm=0.04,
                T_robot_from_optical=RigidTransform.identity(),
                reference_optical_mm=np.zeros((6, 3)),
            )
    log.close(final_state="done", states=["idle", *STATES])
    return path
