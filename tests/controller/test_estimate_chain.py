"""The setpoint's frame chain (``Estimate.desired_tcp_robot_local``): the same pose as the
chain composed in full, and rebuilt whenever one of its parts is replaced."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.controller.planning import GuidePlan
from hil.controller.registration import RobotRegistration
from hil.geometry.transform import RigidTransform
from tests.controller.fakes import chain_estimate
from tests.geometry.strategies import rigid_transforms


def _assert_same(a: RigidTransform, b: RigidTransform) -> None:
    np.testing.assert_allclose(a.R, b.R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-9)   # mm, poses up to a few metres


@settings(max_examples=200, deadline=None)
@given(rigid_transforms(), rigid_transforms(), rigid_transforms(), rigid_transforms(), rigid_transforms())
def test_local_chain_is_the_full_chain(T_ro: RigidTransform, T_rt: RigidTransform, T_center: RigidTransform,
                                       T_bias: RigidTransform, T_local: RigidTransform) -> None:
    est = chain_estimate(T_ro, T_rt, T_center, T_bias)
    _assert_same(est.desired_tcp_robot_local(T_local), est.desired_tcp_robot(est.global_(T_local)))


PARTS = ["T_bias", "robot_reg", "guide_plan", "T_center"]


@settings(max_examples=50, deadline=None)
@given(rigid_transforms(), rigid_transforms(), st.sampled_from(PARTS))
def test_replacing_a_part_rebuilds_the_chain(T_new: RigidTransform, T_local: RigidTransform,
                                             part: str) -> None:
    base = RigidTransform.from_translation((10.0, -20.0, 300.0))
    est = chain_estimate(base, RigidTransform.from_rotvec((0.0, 0.2, 0.0), (0.0, 100.0, 200.0)),
                    RigidTransform.from_translation((5.0, 5.0, 5.0)), RigidTransform.identity())
    est.desired_tcp_robot_local(T_local)   # the chain is built and kept
    if part == "robot_reg":
        est.robot_reg = RobotRegistration(T_new, 0.1, 12)
    elif part == "guide_plan":
        assert est.guide_plan is not None
        est.guide_plan = GuidePlan(est.guide_plan.entry_robot_mm, est.guide_plan.target_robot_mm,
                                   est.guide_plan.T_robot_from_guide, T_new, None, 20.0)
    else:
        setattr(est, part, T_new)
    _assert_same(est.desired_tcp_robot_local(T_local), est.desired_tcp_robot(est.global_(T_local)))


def test_unchanged_parts_keep_the_chain() -> None:
    est = chain_estimate(RigidTransform.identity(), RigidTransform.identity(), RigidTransform.identity(),
                    RigidTransform.identity())
    est.desired_tcp_robot_local(RigidTransform.identity())
    kept = est._chain
    est.desired_tcp_robot_local(RigidTransform.from_translation((1.0, 2.0, 3.0)))
    assert est._chain is kept
