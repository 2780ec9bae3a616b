"""The truth meter's split of the following error (``TruthMeter.path_sample``, issue 41): the path
the controller follows against the true body when its pair was taken and now, exactly, on a
hand-made truth whose entry moves 5 mm/s along y with the path along z."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from hil.clock import ManualClock
from hil.controller.metrics import FloatArray, TruthMeter
from hil.controller.planning import RigGeometry
from hil.controller.snapshot import ControllerSnapshot
from hil.geometry.transform import RigidTransform
from hil.session.log import SessionLog

STANDOFF_MM = 30.0
ENTRY_MM = np.array([0.0, 0.0, 100.0])
DEPTH_MM = 80.0
SPEED_MM_S = 5.0


class _MovingTruth:
    """Entry at ENTRY_MM + (0, 5 mm/s * t, 0), target DEPTH_MM further along +z."""

    T_optical_from_robot = RigidTransform.identity()

    def entry_optical(self, t_ns: int) -> FloatArray:
        return ENTRY_MM + np.array([0.0, SPEED_MM_S * t_ns * 1e-9, 0.0], dtype=np.float64)

    def target_optical(self, t_ns: int) -> FloatArray:
        return self.entry_optical(t_ns) + np.array([0.0, 0.0, DEPTH_MM], dtype=np.float64)

    def body_rigid_residual_mm(self, t_ns: int) -> float:
        return 0.0

    def T_optical_from_flange(self, t_ns: int) -> RigidTransform | None:
        return None


def _snapshot(path: FloatArray | None, path_t_ns: int | None, t_ns: int) -> ControllerSnapshot:
    return ControllerSnapshot(
        t_ns=t_ns, t_s=t_ns * 1e-9, state="compensate", sub_state="tracking", pending=None,
        pending_reason="", last_reason="", started=True, timeline=(), fre_mm=None, tre_expected_mm=None,
        robot_fre_mm=None, T_optical_from_image=None, T_robot_from_optical=None,
        T_bias=RigidTransform.identity(), T_change_meas=None, T_image_from_guide=None,
        reference_optical_mm=None, live_mm=None, flange_mm=None, gate_deviation_mm=None,
        guide_error_mm=None, robot=None, standoff_mm=STANDOFF_MM, path_optical_mm=path, path_t_ns=path_t_ns)


@pytest.fixture
def meter(tmp_path: Path) -> Iterator[TruthMeter]:
    rig = RigGeometry(RigidTransform.identity(), np.zeros((3, 3)))   # the path sample reads no rig
    with SessionLog(tmp_path / "s.jsonl", ManualClock()) as session:
        yield TruthMeter(_MovingTruth(), rig, session)


def test_a_path_exact_at_its_pair_errs_only_by_the_motion_since(meter: TruthMeter) -> None:
    t_pair, t_now = 1_000_000_000, 1_100_000_000
    truth = _MovingTruth()
    path = np.vstack([truth.entry_optical(t_pair), truth.target_optical(t_pair)])
    got = meter.path_sample(_snapshot(path, t_pair, t_now))
    assert got is not None
    assert (got.standoff_at_pair_mm, got.entry_at_pair_mm, got.direction_at_pair_deg) == (0.0, 0.0, 0.0)
    assert got.standoff_now_mm == pytest.approx(SPEED_MM_S * 0.1, abs=1e-12)


def test_an_entry_offset_and_a_tilt_split_into_their_parts(meter: TruthMeter) -> None:
    t_pair = 2_000_000_000
    truth = _MovingTruth()
    entry = truth.entry_optical(t_pair) + np.array([0.3, 0.0, 0.0])
    target = entry + np.array([8.0, 0.0, DEPTH_MM])       # tilted by atan(8 / 80) about y
    tilt = math.atan2(8.0, DEPTH_MM)
    got = meter.path_sample(_snapshot(np.vstack([entry, target]), t_pair, t_pair))
    assert got is not None
    assert got.entry_at_pair_mm == pytest.approx(0.3, abs=1e-12)
    assert got.direction_at_pair_deg == pytest.approx(math.degrees(tilt), abs=1e-12)
    # the stand-off point: 0.3 mm across, less the tilt's swing of the stand-off arm
    swing = math.hypot(0.3 - STANDOFF_MM * math.sin(tilt), STANDOFF_MM - STANDOFF_MM * math.cos(tilt))
    assert got.standoff_at_pair_mm == pytest.approx(swing, abs=1e-12)
    assert got.standoff_now_mm == pytest.approx(swing, abs=1e-12)   # taken now: nothing moved since


def test_no_path_yet_gives_no_sample(meter: TruthMeter) -> None:
    assert meter.path_sample(_snapshot(None, None, 1)) is None
