"""Unit tests of the step logic: planning, gate, compensation, registration."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.interfaces.robot import MotionLimits
from hil.controller.compensation import (
    MotionFilter,
    RateLimiter,
    correction_out_of_bounds,
    rigid_change,
)
from hil.controller.config import (
    CompensationConfig,
    GateConfig,
    PlanningConfig,
    ProcedureConfig,
    RegistrationConfig,
)
from hil.controller.gate import BreathHoldGate, rms_deviation_mm
from hil.controller.plan_file import ProcedurePlan, load_plan, plan_from_dict
from hil.controller.planning import PlanRefusedError, RigGeometry, guide_pose_on_path, plan_guide
from hil.controller.registration import (
    RegistrationFailedError,
    average_identified,
    identify,
    register_patient,
    register_robot,
    track,
)
from hil.errors import GeometryError, InputFileError
from hil.geometry.transform import RigidTransform
from hil.kinematics.ur import ur_forward

RIG = RigGeometry(RigidTransform.from_translation((0.0, 0.0, 60.0)),
                  np.array([[40.0, 90.0, 10.0], [-35.0, 105.0, 10.0], [-10.0, 140.0, 10.0],
                            [30.0, 150.0, 25.0]]))
LIMITS = MotionLimits()
FIDUCIALS = np.array([[0.0, 0.0, 0.0], [60.0, 5.0, -3.0], [-20.0, 55.0, -8.0], [35.0, -45.0, -5.0],
                      [-50.0, -30.0, -10.0], [10.0, 70.0, -12.0]])


# ------------------------------------------------------------------ planning
class TestPlanning:
    def test_guide_axis_runs_along_the_path_with_the_standoff(self) -> None:
        entry, target = np.array([10.0, 20.0, 30.0]), np.array([10.0, 20.0, -50.0])
        T = guide_pose_on_path(entry, target, 25.0)
        np.testing.assert_allclose(T.R[:, 2], [0.0, 0.0, -1.0], atol=1e-12)
        np.testing.assert_allclose(T.t, [10.0, 20.0, 55.0], atol=1e-12)
        np.testing.assert_allclose(T.R.T @ T.R, np.eye(3), atol=1e-12)
        assert np.linalg.det(T.R) == pytest.approx(1.0)

    def test_roll_follows_the_hint(self) -> None:
        T = guide_pose_on_path(np.zeros(3), np.array([0.0, 0.0, -10.0]), 0.0,
                               x_hint=np.array([0.0, 1.0, 0.3]))
        np.testing.assert_allclose(T.R[:, 0], [0.0, 1.0, 0.0], atol=1e-12)

    def test_coincident_entry_and_target_is_refused(self) -> None:
        with pytest.raises(PlanRefusedError, match="coincide"):
            plan_guide(np.zeros(3), np.zeros(3), RIG, PlanningConfig(), LIMITS)

    def test_a_reachable_pose_gets_an_ik_solution_that_reproduces_it(self) -> None:
        q0 = np.array([1.9513, -1.4523, -1.8396, -1.4204, 1.5708, 0.3805])
        T_flange = ur_forward(q0)
        T_guide = T_flange @ RIG.T_flange_from_guide
        entry = T_guide.t + 30.0 * T_guide.R[:, 2]
        target = entry + 70.0 * T_guide.R[:, 2]
        gp = plan_guide(entry, target, RIG, PlanningConfig(standoff_mm=30.0), LIMITS, q_near=q0)
        assert gp.q_rad is not None
        assert ur_forward(gp.q_rad).is_close(gp.T_robot_from_tcp, atol_mm=1e-6, atol_rad=1e-6)
        np.testing.assert_allclose(gp.T_robot_from_guide.t, T_guide.t, atol=1e-9)
        np.testing.assert_allclose(gp.axis_robot, T_guide.R[:, 2], atol=1e-12)

    def test_outside_the_workspace_box_is_refused_with_the_reason(self) -> None:
        with pytest.raises(PlanRefusedError, match="outside the workspace box"):
            plan_guide(np.array([0.0, 0.0, 900.0]), np.array([0.0, 0.0, 800.0]), RIG,
                       PlanningConfig(), LIMITS)

    def test_beyond_reach_is_refused(self) -> None:
        limits = MotionLimits(workspace_min_mm=(-2000.0,) * 3, workspace_max_mm=(2000.0,) * 3)
        with pytest.raises(PlanRefusedError, match="beyond the ur3 reach"):
            plan_guide(np.array([900.0, 0.0, 100.0]), np.array([900.0, 0.0, 0.0]), RIG,
                       PlanningConfig(), limits)

    def test_no_ik_solution_is_refused(self) -> None:
        # right above the base axis: the shoulder offset d4 makes it unreachable
        with pytest.raises(PlanRefusedError, match="no inverse-kinematics solution"):
            plan_guide(np.array([0.0, 0.0, 300.0]), np.array([0.0, 0.0, 200.0]), RIG,
                       PlanningConfig(standoff_mm=0.0), LIMITS)


# ------------------------------------------------------------------ plan file
class TestPlanFile:
    DOC: ClassVar[dict[str, Any]] = {
        "format": "hil-plan", "version": 1, "frame": "image", "units": "mm",
        "fiducials_mm": FIDUCIALS.tolist(), "entry_mm": [0.0, 0.0, 0.0], "target_mm": [0.0, 0.0, -70.0]}

    def test_valid(self) -> None:
        p = plan_from_dict(self.DOC, "x.json")
        assert p.fiducials_mm.shape == (6, 3)
        assert p.path_length_mm == pytest.approx(70.0)

    @pytest.mark.parametrize(("change", "message"), [
        ({"format": "other"}, "format: expected 'hil-plan'"),
        ({"version": 2}, "version: unsupported 2"),
        ({"units": "m"}, "units: expected 'mm'"),
        ({"entry_mm": [1.0, 2.0]}, "entry_mm: "),
        ({"fiducials_mm": [[0.0, 0.0, 0.0]]}, "needs >= 3 fiducials"),
        ({"target_mm": [0.0, 0.0, 0.5]}, "less than 1 mm apart"),
        ({"fiducials_mm": [[0.0, 0.0, float("nan")]] * 3}, "fiducials_mm: "),
    ])
    def test_invalid_names_file_and_field(self, change: dict[str, object], message: str) -> None:
        with pytest.raises(InputFileError, match=r"x\.json") as ei:
            plan_from_dict({**self.DOC, **change}, "x.json")
        assert message in str(ei.value)

    def test_bundled_sim_plan_loads(self) -> None:
        p = load_plan("configs/plans/sim_plan.json")
        assert p.fiducials_mm.shape[0] >= 3

    def test_missing_and_garbage_files(self, tmp_path: object) -> None:
        import pathlib
        d = pathlib.Path(str(tmp_path))
        with pytest.raises(InputFileError, match="cannot read plan"):
            load_plan(d / "nope.json")
        (d / "bad.json").write_text("{", encoding="utf-8")
        with pytest.raises(InputFileError, match="not JSON"):
            load_plan(d / "bad.json")


# ------------------------------------------------------------------ gate
class TestGate:
    CFG = GateConfig(tolerance_mm=1.0, dwell_s=0.5, timeout_s=2.0)

    def test_opens_after_the_dwell_and_not_before(self) -> None:
        g = BreathHoldGate(self.CFG, FIDUCIALS)
        g.restart(0)
        live = FIDUCIALS + 0.3
        states = [g.update(live, int(k * 0.1e9)).open for k in range(7)]
        assert states == [False, False, False, False, False, True, True]

    def test_an_excursion_restarts_the_dwell(self) -> None:
        g = BreathHoldGate(self.CFG, FIDUCIALS)
        g.restart(0)
        for k in range(4):
            g.update(FIDUCIALS, int(k * 0.1e9))
        s = g.update(FIDUCIALS + 2.0, int(0.4e9))
        assert (s.open, s.dwell_s) == (False, 0.0)
        assert "closed: markers 3.46 mm RMS" in s.justification
        assert not g.update(FIDUCIALS, int(0.5e9)).open
        assert g.update(FIDUCIALS, int(1.0e9)).open

    def test_timeout_is_reported_once_with_a_message(self) -> None:
        g = BreathHoldGate(self.CFG, FIDUCIALS)
        g.restart(0)
        outs = [g.update(FIDUCIALS + 5.0, int(t * 1e9)) for t in (1.0, 2.1, 2.2)]
        assert [o.timed_out for o in outs] == [False, True, False]
        assert "no breath-hold within 2.0 s" in outs[1].justification
        g.restart(int(2.2e9))
        assert not g.update(FIDUCIALS + 5.0, int(3.0e9)).timed_out

    def test_too_few_markers_keep_it_closed(self) -> None:
        g = BreathHoldGate(GateConfig(tolerance_mm=1.0, dwell_s=0.0, timeout_s=5.0), FIDUCIALS)
        live = FIDUCIALS.copy()
        live[2:] = np.nan
        s = g.update(live, 0)
        assert (s.open, s.markers) == (False, 2)
        assert g.update(None, 1).deviation_rms_mm == math.inf

    def test_rms_deviation_ignores_missing_rows(self) -> None:
        live = FIDUCIALS + np.array([3.0, 4.0, 0.0])
        live[0] = np.nan
        assert rms_deviation_mm(FIDUCIALS, live) == (pytest.approx(5.0), 5)


# ------------------------------------------------------------------ compensation
@settings(max_examples=30, deadline=None)
@given(rv=st.tuples(*[st.floats(-0.2, 0.2)] * 3), t=st.tuples(*[st.floats(-30.0, 30.0)] * 3))
def test_rigid_change_recovers_the_motion(rv: tuple[float, float, float],
                                          t: tuple[float, float, float]) -> None:
    """Horn on reference -> live gives back the applied rigid motion (seed 000 eqs 17-21)."""
    T = RigidTransform.from_rotvec(rv, t)
    reg = rigid_change(FIDUCIALS, T.apply(FIDUCIALS))
    assert reg is not None
    assert reg.T_fixed_from_moving.is_close(T, atol_mm=1e-8, atol_rad=1e-9)


def test_rigid_change_needs_three_markers() -> None:
    live = FIDUCIALS.copy()
    live[2:] = np.nan
    assert rigid_change(FIDUCIALS, live) is None
    live = FIDUCIALS.copy()
    live[3:] = np.nan
    assert rigid_change(FIDUCIALS, live) is not None


def test_bounds() -> None:
    cfg = CompensationConfig(max_correction_mm=10.0, max_correction_deg=5.0)
    assert correction_out_of_bounds(RigidTransform.from_translation((6.0, 8.0, 0.0)), cfg) is None
    moved = correction_out_of_bounds(RigidTransform.from_translation((6.0, 8.0, 2.0)), cfg)
    turned = correction_out_of_bounds(RigidTransform.from_rotvec((0.1, 0.0, 0.0)), cfg)
    assert moved == "patient moved 10.2 mm from the registered state (bound 10.0 mm)"
    assert turned == "patient turned 5.7 deg from the registered state (bound 5.0 deg)"


def test_motion_filter_tracks_and_predicts_a_constant_velocity() -> None:
    f = MotionFilter(0.7, 0.3)
    v = np.array([10.0, 0.0, -5.0])  # mm/s
    for k in range(60):
        f.update(RigidTransform.from_translation(v * k / 15.0), round(k / 15.0 * 1e9))
    t_last = round(59 / 15.0 * 1e9)
    np.testing.assert_allclose(f.estimate().t, v * 59 / 15.0, atol=1e-6)
    np.testing.assert_allclose(f.estimate(t_last + 100_000_000, 0.15).t, v * (59 / 15.0 + 0.1), atol=1e-6)
    np.testing.assert_allclose(f.estimate(t_last + 900_000_000, 0.15).t, v * (59 / 15.0 + 0.15), atol=1e-6)
    assert f.speed_mm_s == pytest.approx(float(np.linalg.norm(v)), rel=1e-6)


def test_motion_filter_without_samples_refuses() -> None:
    with pytest.raises(GeometryError, match="no sample"):
        MotionFilter(0.5, 0.1).estimate()


class TestRateLimiter:
    def test_reaches_a_static_target_without_overshoot_within_limits(self) -> None:
        rl = RateLimiter(50.0, 200.0, 0.5)
        rl.reset(RigidTransform.identity())
        goal = RigidTransform.from_rotvec((0.0, 0.0, 0.2), (30.0, 0.0, 0.0))
        xs, vs = [0.0], [0.0]
        for _ in range(400):
            c = rl.step(goal, 0.01)
            xs.append(float(c.t[0]))
            vs.append(float(rl.velocity_mm_s[0]) if rl.velocity_mm_s is not None else 0.0)
        assert max(xs) <= 30.0 + 1e-9
        assert xs[-1] == pytest.approx(30.0, abs=1e-6)
        assert max(np.abs(np.diff(xs)) / 0.01) <= 50.0 + 1e-9
        assert max(np.abs(np.diff(vs)) / 0.01) <= 200.0 + 1e-6
        assert rl.command is not None
        assert rl.command.rotation_angle_rad() == pytest.approx(0.2, abs=1e-9)

    def test_speed_scale_ramps_the_speed(self) -> None:
        rl = RateLimiter(50.0, 10_000.0, 0.5)
        rl.reset(RigidTransform.identity())
        c = rl.step(RigidTransform.from_translation((100.0, 0.0, 0.0)), 0.1, speed_scale=0.1)
        assert float(c.t[0]) == pytest.approx(0.5)

    def test_rotation_is_acceleration_limited_and_does_not_overshoot(self) -> None:
        rl = RateLimiter(50.0, 200.0, 0.5, 2.0)
        rl.reset(RigidTransform.identity())
        goal = RigidTransform.from_rotvec((0.0, 0.0, 0.2), (0.0, 0.0, 0.0))
        angles = [0.0]
        for _ in range(300):
            c = rl.step(goal, 0.008)
            angles.append(float(c.as_rotvec()[2]))
        w = np.diff(angles) / 0.008
        assert max(angles) <= 0.2 + 1e-9
        assert angles[-1] == pytest.approx(0.2, abs=1e-9)
        assert float(np.abs(np.diff(w)).max()) / 0.008 <= 2.0 + 1e-6   # the angular acceleration limit
        assert float(w.max()) <= 0.5                                        # the angular speed limit
        assert float(w[0]) == pytest.approx(2.0 * 0.008 * 0.999)           # from rest, not at 0.5 rad/s

    def test_attitude_noise_reaches_the_arm_damped(self) -> None:
        # the target's attitude jitters by +-1.5 mrad from pair to pair (every 4 periods at 125 Hz)
        rng = np.random.default_rng(1)

        def peak_rate(rl: RateLimiter) -> float:
            rl.reset(RigidTransform.identity())
            angles = [0.0]
            goal = RigidTransform.identity()
            for k in range(400):
                if k % 4 == 0:
                    jitter_rad = float(rng.uniform(-1.5e-3, 1.5e-3))
                    goal = RigidTransform.from_rotvec((jitter_rad, 0.0, 0.0), np.zeros(3))
                angles.append(float(rl.step(goal, 0.008).as_rotvec()[0]))
            return float(np.abs(np.diff(angles)).max() / 0.008)

        assert peak_rate(RateLimiter(50.0, 200.0, 0.5)) > 0.3                 # bursts at the speed limit
        assert peak_rate(RateLimiter(50.0, 200.0, 0.5, 2.0)) < 0.08           # sqrt(a * 3 mrad) order

    def test_speed_scale_ramps_the_rotation_too(self) -> None:
        rl = RateLimiter(50.0, 10_000.0, 0.5)
        rl.reset(RigidTransform.identity())
        c = rl.step(RigidTransform.from_rotvec((0.0, 0.0, 1.0), np.zeros(3)), 0.1, speed_scale=0.1)
        assert c.rotation_angle_rad() == pytest.approx(0.5 * 0.1 * 0.1 * 0.999)

    def test_not_reset_refuses(self) -> None:
        with pytest.raises(GeometryError, match="not reset"):
            RateLimiter(1.0, 1.0, 1.0).step(RigidTransform.identity(), 0.1)


# ------------------------------------------------------------------ registration
T_OPT_FROM_IMG = RigidTransform.from_rotvec((math.pi, 0.0, 0.1), (60.0, 0.0, 1000.0))
PLAN = ProcedurePlan(FIDUCIALS, np.zeros(3), np.array([10.0, 8.0, -75.0]))


def _frames(n: int, noise_mm: float, seed: int = 0, extra: int = 2) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        pts = T_OPT_FROM_IMG.apply(FIDUCIALS) + rng.normal(0, noise_mm, FIDUCIALS.shape)
        spurious = rng.uniform(-300, 300, (extra, 3)) + np.array([0.0, 0.0, 1000.0])
        pts = np.vstack([pts, spurious])
        out.append(rng.permutation(pts))
    return out


class TestRegistration:
    def test_identify_and_register(self) -> None:
        ident = [identify(f, FIDUCIALS, 3.0) for f in _frames(10, 0.05)]
        assert all(i is not None for i in ident)
        reg = register_patient([i for i in ident if i is not None], PLAN, RegistrationConfig())
        assert reg.T_optical_from_image.is_close(T_OPT_FROM_IMG, atol_mm=0.1, atol_rad=1e-3)
        assert 0 < reg.fre_rms_mm < 0.05
        assert 0 < reg.tre_expected_mm < 1.0
        assert (reg.markers_used, reg.frames) == (6, 10)

    def test_fre_over_threshold_fails_with_the_reason(self) -> None:
        ident = [identify(f, FIDUCIALS, 5.0) for f in _frames(3, 1.0)]
        with pytest.raises(RegistrationFailedError, match=r"FRE .* exceeds 0\.1 mm"):
            register_patient([i for i in ident if i is not None], PLAN, RegistrationConfig(fre_max_mm=0.1))

    def test_too_few_markers_fails(self) -> None:
        ident = identify(_frames(1, 0.0)[0], FIDUCIALS, 3.0)
        assert ident is not None
        ident[:3] = np.nan
        with pytest.raises(RegistrationFailedError, match="only 3 skin markers"):
            register_patient([ident], PLAN, RegistrationConfig(min_markers=4))

    def test_average_drops_rarely_seen_markers(self) -> None:
        a = np.ones((2, 3))
        b = np.ones((2, 3)) * 3
        b[1] = np.nan
        c = np.ones((2, 3)) * 5
        c[1] = np.nan
        avg = average_identified([a, b, c])
        np.testing.assert_allclose(avg[0], [3.0, 3.0, 3.0])
        assert np.all(np.isnan(avg[1]))

    def test_track_assigns_nearest_uniquely(self) -> None:
        pred = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [np.nan] * 3])
        pts = np.array([[10.5, 0.0, 0.0], [0.2, 0.0, 0.0], [50.0, 0.0, 0.0]])
        out = track(pts, pred, 2.0)
        np.testing.assert_allclose(out[:2], pts[[1, 0]])
        assert np.all(np.isnan(out[2]))

    def test_robot_registration_recovers_the_hand_eye(self) -> None:
        T_optical_from_robot = RigidTransform.from_rotvec((math.pi, 0.0, 0.0), (60.0, 300.0, 1120.0))
        T_robot_from_optical = T_optical_from_robot.inverse()
        poses = [RigidTransform.from_rotvec((0.1 * k, 0.0, 0.0), (100.0 + 10 * k, 50.0, 200.0))
                 for k in range(3)]
        obs = [T_robot_from_optical.inverse().apply(T.apply(RIG.flange_markers_tcp_mm)) for T in poses]
        reg = register_robot(obs, poses, RIG.flange_markers_tcp_mm)
        assert reg.T_robot_from_optical.is_close(T_robot_from_optical, atol_mm=1e-8, atol_rad=1e-10)
        assert reg.pairs == 12

    def test_robot_registration_without_markers_fails(self) -> None:
        with pytest.raises(RegistrationFailedError, match="flange markers not seen"):
            register_robot([np.full((4, 3), np.nan)], [RigidTransform.identity()], RIG.flange_markers_tcp_mm)


def test_default_procedure_config_is_consistent() -> None:
    cfg = ProcedureConfig()
    assert cfg.lock.drift_alarm_mm > cfg.lock.tolerance_mm
    with pytest.raises(ValueError, match="drift_alarm_mm must be larger"):
        ProcedureConfig.model_validate({"lock": {"tolerance_mm": 3.0, "drift_alarm_mm": 2.0}})
    with pytest.raises(ValueError, match="Extra inputs"):
        ProcedureConfig.model_validate({"bogus": 1})


@pytest.mark.parametrize(("doc", "where"), [
    ({"max_duration_s": float("inf")}, "max_duration_s"),
    ({"gate": {"timeout_s": float("inf")}}, "gate.timeout_s"),
    ({"compensation": {"max_correction_mm": float("nan")}}, "compensation.max_correction_mm"),
])
def test_infinite_or_nan_procedure_values_are_refused(doc: dict[str, Any], where: str) -> None:
    """``max_duration_s = inf`` would never end a run; NaN compares false with every bound."""
    with pytest.raises(ValueError, match="finite number") as ei:
        ProcedureConfig.model_validate(doc)
    assert where in str(ei.value)
