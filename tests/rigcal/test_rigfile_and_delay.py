"""The rig calibration file's validation, the delay estimator, and the time-aligning adapters."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.interfaces import FrameTime
from hil.clock import ManualClock
from hil.config import SetupConfig, build_devices
from hil.errors import InputFileError
from hil.rigcal.delay import Reference, estimate_delay
from hil.rigcal.rigfile import RigCalibration, TimeOffset, load_rig_calibration
from hil.rigcal.time_align import time_aligned
from plugins.registry import DriverRegistry

HAND_EYE: dict[str, Any] = {"flange_markers_mm": [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 10.0]]}
GOOD: dict[str, Any] = {"schema": "hil.rig_calibration", "version": 1, "hand_eye": HAND_EYE,
                        "time_offsets": {"camera": {"offset_ms": 45.0, "sigma_ms": 0.2}}}


def _write(tmp_path: Path, doc: object) -> Path:
    p = tmp_path / "rig.json"
    p.write_text(json.dumps(doc))
    return p


def test_a_valid_file_loads(tmp_path: Path) -> None:
    rig = load_rig_calibration(_write(tmp_path, GOOD))
    assert rig.flange_markers_mm is not None
    assert rig.flange_markers_mm.tolist() == HAND_EYE["flange_markers_mm"]
    assert rig.time_offsets == {"camera": TimeOffset(45.0, 0.2)}
    assert rig.offset_ns("camera") == 45_000_000
    assert rig.offset_ns("robot") == 0


@pytest.mark.parametrize(("change", "message"), [
    ({"schema": "other"}, "not a rig calibration file"),
    ({"version": 2}, "rig calibration version 2 is not supported"),
    ({"hand_eye": {"flange_markers_mm": [[1, 2, 3]]}}, "list of >= 3"),
    ({"hand_eye": None, "time_offsets": None}, "neither a hand_eye nor a time_offsets part"),
    ({"time_offsets": {"lidar": {"offset_ms": 1}}}, "time_offsets.lidar: unknown device"),
    ({"time_offsets": {"robot": {"offset_ms": "x"}}}, "time_offsets.robot.offset_ms must be a finite number"),
    ({"hand_eye": {**HAND_EYE, "optical_correction": [[1, 0, 0]]}},
     r"hand_eye.optical_correction must be a 4x4 matrix"),
    ({"hand_eye": {**HAND_EYE, "optical_correction": [[1, 0, 0, 0]] * 3 + [[0, 0, 0, None]]}},
     r"hand_eye.optical_correction\[3\]\[3\] must be a finite number"),
    ({"hand_eye": {**HAND_EYE, "optical_correction": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                              [0, 0, 0, 0]]}},
     r"hand_eye.optical_correction: a projective correction needs H\[3\]\[3\] != 0"),
    ({"hand_eye": {**HAND_EYE, "optical_correction": [[1.2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                              [0, 0, 0, 1]]}},
     r"hand_eye.optical_correction is too far from the identity \(linear part off by 0.2, bound 0.05"),
    ({"hand_eye": {**HAND_EYE, "optical_correction": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                              [0, 0, 0.001, 1]]}},
     r"projective row 0.001/mm, bound 0.0001/mm"),
])
def test_a_bad_file_names_what_is_wrong(tmp_path: Path, change: dict[str, object], message: str) -> None:
    with pytest.raises(InputFileError, match=message):
        load_rig_calibration(_write(tmp_path, {**GOOD, **change}))


def test_an_optical_correction_loads_normalised(tmp_path: Path) -> None:
    H = [[2.002, 0.0, 0.0, 1.0], [0.0, 2.0, 0.0, -4.0], [0.0, 0.0, 1.998, 6.0], [0.0, 0.0, 2e-6, 2.0]]
    rig = load_rig_calibration(_write(tmp_path, {**GOOD, "hand_eye": {**HAND_EYE,
                                                                      "optical_correction": H}}))
    assert rig.optical_correction is not None
    np.testing.assert_array_equal(rig.optical_correction.H_metric_from_measured, np.array(H) / 2.0)
    assert load_rig_calibration(_write(tmp_path, GOOD)).optical_correction is None


def test_not_json(tmp_path: Path) -> None:
    p = tmp_path / "rig.json"
    p.write_text("{")
    with pytest.raises(InputFileError, match="not JSON: line 1"):
        load_rig_calibration(p)


@settings(max_examples=25, deadline=None)
@given(st.floats(-150.0, 150.0), st.floats(0.05, 0.5))
def test_delay_of_a_delayed_copy_is_recovered(delay_ms: float, noise_mm: float) -> None:
    rng = np.random.default_rng(0)
    t_cmd = np.arange(0, 8e9, 8e6)
    v_cmd = 15.0 * np.sin(2 * math.pi * 0.5 * t_cmd * 1e-9)
    ref = Reference(t_cmd, v_cmd)
    t_dev = np.sort(rng.uniform(0.5e9, 7.5e9, size=200))
    held = np.searchsorted(t_cmd, t_dev - delay_ms * 1e6, side="right") - 1   # the arm holds each command
    true = v_cmd[held]
    y = -2.0 * true + 7.0 + noise_mm * rng.normal(size=t_dev.size)   # any gain and bias
    est = estimate_delay(ref, t_dev, y, 250.0, "camera")
    assert abs(est.delay_ms - delay_ms) < max(5 * est.sigma_ms, 0.3)
    assert est.sigma_ms < 1.0


def test_adapters_subtract_the_offsets(realistic: SetupConfig, registry: DriverRegistry) -> None:
    clock = ManualClock(start_ns=1_000_000_000)
    raw = build_devices(realistic, clock, registry)
    rig = RigCalibration(None, time_offsets={"camera": TimeOffset(45.0, 0.1), "robot": TimeOffset(8.0, 0.1),
                                "tracker": TimeOffset(20.0, 0.1)})
    cam, rob, trk = time_aligned(raw.camera, raw.robot, raw.tracker, rig)
    assert trk is not None
    for d in (cam, rob, trk):
        d.open()
    try:
        pair = cam.grab(1.0)
        exposure = raw.camera.exposure_time_ns(pair.left.seq)  # type: ignore[attr-defined]
        assert abs(pair.left.t_ns - exposure) <= 3_000_000        # the jitter only
        assert pair.left.time_source is FrameTime.EXPOSURE
        assert rob.state_now().t_ns == clock.now_ns() - 8_000_000
        assert rob.T_flange_from_tcp is raw.robot.T_flange_from_tcp  # the interface passes through
        s = trk.latest()["reference"]
        assert s.t_ns == raw.tracker.latest()["reference"].t_ns - 20_000_000
    finally:
        for d in (rob, cam, trk):
            d.close()
    assert raw.robot.state.value == "closed"
