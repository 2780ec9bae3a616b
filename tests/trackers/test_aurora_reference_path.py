"""The procedure's reference-sensor path fed by the real Aurora driver on the emulator.

Contract (hil/controller/tracker_use.py, tracker_roles.py, docs/run.md "The tracker"): a sample is
usable only when it is not missing and has a pose; the reference's pose is taken at registration
(``reference_sensor_recorded`` with ``available``); its rigid change stands in for the skin
markers when they give none (``reference_in_use``) and is compared with them when both give one.
So a reference that is MISSING or out of volume gives no change: it neither stands in (the estimate
keeps no change) nor is compared, and nothing of its last pose is used; when it is back it is
used again. A stale tracker is not the path's business: ``latest()`` raises (the controller's
tracker watchdog and fault handling act on it).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from drivers.interfaces.errors import DeviceTimeoutError
from drivers.tracker_serial.aurora import AuroraTracker
from drivers.tracker_serial.config import AuroraConfig
from hil.clock import MonotonicClock
from hil.controller.config import TrackingConfig
from hil.controller.fsm import State
from hil.controller.tracker_roles import TrackerRoles
from hil.controller.tracker_use import TrackerUse
from hil.geometry.transform import RigidTransform
from hil.session.log import SessionLog

from .conftest import AuroraFactory, wait_until

T_OPTICAL_FROM_TRACKER = RigidTransform(RigidTransform.from_euler_zyx(0.0, 0.0, np.pi).R,
                                        np.array([-190.0, 0.0, 1100.0]))
ENTRY_IMAGE_MM = np.array([5.0, -10.0, 0.0])


@pytest.fixture
def aurora(aurora_emulator: AuroraFactory) -> Iterator[tuple[Any, AuroraTracker]]:
    dev = aurora_emulator()
    cfg = AuroraConfig.model_validate({
        "driver": "aurora", "port": dev.link.path, "sensors": {"reference": "0A", "needle": "0B"},
        "break_as_nul": True, "reset_timeout_s": 2.0, "response_timeout_s": 0.3, "timeout_s": 0.3,
        "poll_rate_hz": 100.0, "reinit_after_s": None})
    tracker = AuroraTracker(cfg)
    with tracker:
        wait_until(lambda: "reference" in tracker.latest(), what="first frame")
        yield dev, tracker


class _Session:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.log = SessionLog(path, MonotonicClock(), {"test": "reference path"})

    def events(self, name: str) -> list[dict[str, Any]]:
        out = []
        for line in self.path.read_text().splitlines():
            rec = json.loads(line)
            if rec.get("event") == name:
                out.append(rec)
        return out


def _estimate(samples: dict[str, Any], change: RigidTransform | None) -> SimpleNamespace:
    """What TrackerRoles.reference_sensor reads of the controller's estimate."""
    return SimpleNamespace(
        tracker_samples=samples, T_change_meas=change,
        patient_reg=SimpleNamespace(T_optical_from_image=RigidTransform.identity()),
        plan=SimpleNamespace(entry_mm=ENTRY_IMAGE_MM))


def _roles(tmp_path: Path) -> tuple[TrackerRoles, _Session]:
    session = _Session(tmp_path / "session.jsonl")
    use = TrackerUse(TrackingConfig(reference_sensor="reference"), T_OPTICAL_FROM_TRACKER)
    return TrackerRoles(use, session.log), session


@pytest.mark.parametrize("fault", ["tool_missing,handles=0A", "out_of_volume,handles=0A"])
def test_a_reference_lost_after_registration_neither_stands_in_nor_is_compared(
        aurora: tuple[Any, AuroraTracker], tmp_path: Path, fault: str) -> None:
    dev, tracker = aurora
    roles, session = _roles(tmp_path)
    roles.record_reference(_estimate(tracker.latest(), None))
    assert [r["available"] for r in session.events("reference_sensor_recorded")] == [True]

    # present, markers give no change: the reference stands in (a static reference: no motion)
    est = _estimate(tracker.latest(), None)
    roles.reference_sensor(est, State.COMPENSATE)
    assert est.T_change_meas is not None
    assert est.T_change_meas.rotation_angle_rad() < 1e-6
    np.testing.assert_allclose(est.T_change_meas.t, 0.0, atol=1e-3)
    assert len(session.events("reference_in_use")) == 1

    dev.faults.inject(fault, dev.now_s())
    wait_until(lambda: tracker.latest()["reference"].missing, what="the reference lost")
    samples = tracker.latest()
    assert not samples["needle"].missing  # the other tool still tracked: no tracker error
    # lost, markers give no change: nothing stands in, no stale pose used
    est = _estimate(samples, None)
    roles.reference_sensor(est, State.COMPENSATE)
    assert est.T_change_meas is None
    assert roles.use is not None
    assert roles.use.reference_change(samples) is None
    # lost, markers give a change 5 mm off: kept as it is, not compared
    markers = RigidTransform.from_translation([5.0, 0.0, 0.0])
    est = _estimate(samples, markers)
    roles.reference_sensor(est, State.COMPENSATE)
    assert est.T_change_meas is markers
    assert session.events("reference_disagreement") == []
    assert session.events("reference_released") == []

    dev.faults.clear()
    wait_until(lambda: not tracker.latest()["reference"].missing, what="the reference back")
    est = _estimate(tracker.latest(), markers)
    roles.reference_sensor(est, State.COMPENSATE)
    assert est.T_change_meas is markers  # the markers' change is kept, the reference compared
    assert len(session.events("reference_released")) == 1
    (dis,) = session.events("reference_disagreement")
    assert dis["entry_difference_mm"] == pytest.approx(5.0, abs=0.01)
    session.log.close()


def test_a_reference_missing_at_registration_is_never_used(aurora: tuple[Any, AuroraTracker],
                                                           tmp_path: Path) -> None:
    dev, tracker = aurora
    roles, session = _roles(tmp_path)
    dev.faults.inject("tool_missing,handles=0A", dev.now_s())
    wait_until(lambda: tracker.latest()["reference"].missing, what="the reference missing")
    roles.record_reference(_estimate(tracker.latest(), None))
    assert [r["available"] for r in session.events("reference_sensor_recorded")] == [False]
    dev.faults.clear()
    wait_until(lambda: not tracker.latest()["reference"].missing, what="the reference back")
    est = _estimate(tracker.latest(), None)
    roles.reference_sensor(est, State.COMPENSATE)
    assert est.T_change_meas is None  # no registration-time pose: nothing to stand in with
    assert session.events("reference_in_use") == []
    session.log.close()


def test_a_stale_tracker_gives_the_path_nothing(aurora: tuple[Any, AuroraTracker]) -> None:
    """A device reset (no re-initialisation here): latest() raises instead of handing over the last
    poses, so the reference path cannot be fed a stale pose."""
    dev, tracker = aurora
    dev.faults.inject("reset", dev.now_s())

    def stale() -> bool:
        try:
            tracker.latest()
        except DeviceTimeoutError:
            return True
        return False

    wait_until(stale, what="DeviceTimeoutError")
    with pytest.raises(DeviceTimeoutError, match="no valid record"):
        tracker.latest()
