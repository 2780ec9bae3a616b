"""OpenIGTLink: the stream received by a pyigtl client on loopback, matrices checked."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from types import SimpleNamespace

import numpy as np
import pyigtl
import pytest
from pydantic import ValidationError

from hil.clock import ManualClock
from hil.controller.snapshot import ControllerSnapshot, guide_in_image
from hil.geometry.transform import RigidTransform
from hil.igtl import IgtlConfig, IgtlSnapshot, igtl_snapshot
from hil.igtl.server import IgtlError, IgtlServer

DEADLINE_S = 5.0


def _wait_until(cond: Callable[[], bool]) -> None:
    """Poll a condition of a real network exchange, bounded by DEADLINE_S."""
    end = time.monotonic() + DEADLINE_S
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("condition not reached within the deadline")
        time.sleep(0.005)


@pytest.fixture
def server() -> Iterator[IgtlServer]:
    srv = IgtlServer(IgtlConfig(enabled=True, port=0), ManualClock())
    srv.start()
    yield srv
    srv.close()


@pytest.fixture
def client(server: IgtlServer) -> Iterator[pyigtl.OpenIGTLinkClient]:
    c = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=server.address[1])
    _wait_until(lambda: server.clients == 1)
    yield c
    c.stop()


def test_config_defaults_and_validation() -> None:
    cfg = IgtlConfig()
    assert (cfg.enabled, cfg.host, cfg.port, cfg.rate_hz) == (False, "127.0.0.1", 18944, 20.0)
    with pytest.raises(ValidationError, match="extra"):
        IgtlConfig.model_validate({"enabled": True, "command_port": 1})
    with pytest.raises(ValidationError, match="not an IPv4 address"):
        IgtlConfig(host="slicer.example")
    with pytest.raises(ValidationError):
        IgtlConfig(port=70000)


def test_binds_loopback_and_port_in_use_is_a_typed_error(server: IgtlServer) -> None:
    host, port = server.address
    assert host == "127.0.0.1"
    assert port > 0
    other = IgtlServer(IgtlConfig(enabled=True, port=port), ManualClock())
    with pytest.raises(IgtlError, match=f"cannot listen on 127.0.0.1:{port}"):
        other.start()


def test_stream_received_matrices_status_points(server: IgtlServer, client: pyigtl.OpenIGTLinkClient) -> None:
    rng = np.random.default_rng(3)
    mats = {name: RigidTransform.from_rotvec(rng.normal(size=3), rng.normal(size=3) * 300.0).as_matrix()
            for name in ("GuideToImage", "ImageToOptical", "PatientToOptical", "ReferenceToTracker")}
    snap = IgtlSnapshot(mats, "state=lock pending=lock_to_done",
                        {"entry": np.array([1.0, 2.0, 3.0]), "target": np.array([4.0, 5.0, -6.5])})
    assert server.publish(snap) == 6
    for name, m in mats.items():
        msg = client.wait_for_message(name, timeout=DEADLINE_S)
        assert msg is not None, name
        assert isinstance(msg, pyigtl.TransformMessage)
        # the wire format is float32: exactly the float32 of what was sent
        np.testing.assert_array_equal(np.asarray(msg.matrix, dtype=np.float32)[:3],
                                      m.astype(np.float32)[:3])
        np.testing.assert_allclose(msg.matrix, m, atol=1e-3)
    st = client.wait_for_message("Status", timeout=DEADLINE_S)
    assert st is not None
    assert st.string == "state=lock pending=lock_to_done"
    pts = client.wait_for_message("Plan", timeout=DEADLINE_S)
    assert pts is not None
    assert list(pts.names) == ["entry", "target"]
    np.testing.assert_allclose(np.asarray(pts.positions, dtype=float), [[1, 2, 3], [4, 5, -6.5]])


def test_rate_limit_on_the_controller_clock(server: IgtlServer, client: pyigtl.OpenIGTLinkClient) -> None:
    snap = IgtlSnapshot({"GuideToImage": np.eye(4)}, "state=gate", {})
    t0 = 1_000_000_000
    assert server.publish(snap, t0) == 2          # transform + status
    assert server.publish(snap, t0 + 10_000_000) == 0   # 10 ms later: nothing due at 20 Hz
    assert server.publish(snap, t0 + 50_000_000) == 1   # 50 ms: transforms again
    assert server.publish(snap, t0 + 500_000_000) == 2  # 0.5 s: status due too (2 Hz)
    assert server.publish(snap, t0 + 510_000_000, force=True) == 2


def test_client_input_is_ignored_and_stream_continues(server: IgtlServer,
                                                      client: pyigtl.OpenIGTLinkClient) -> None:
    client.send_message(pyigtl.TransformMessage(np.eye(4), device_name="RobotTarget"), wait=True)
    client.send_message(pyigtl.StringMessage("abort", device_name="Command"), wait=True)
    _wait_until(lambda: server.ignored_bytes_now() > 0)
    m = np.eye(4)
    m[:3, 3] = [10.0, 20.0, 30.0]
    server.publish(IgtlSnapshot({"GuideToImage": m}), force=True)
    msg = client.wait_for_message("GuideToImage", timeout=DEADLINE_S)
    assert msg is not None
    np.testing.assert_allclose(msg.matrix, m)


def test_no_client_nothing_queued_and_close_is_idempotent() -> None:
    srv = IgtlServer(IgtlConfig(enabled=True, port=0), ManualClock())
    srv.start()
    assert srv.publish(IgtlSnapshot({"GuideToImage": np.eye(4)})) == 0
    srv.close()
    srv.close()


def _fake_estimate(T_optical_from_image: RigidTransform, T_robot_from_optical: RigidTransform,
                   T_change: RigidTransform, T_bias: RigidTransform, T_robot_from_tcp: RigidTransform,
                   T_tcp_from_guide: RigidTransform) -> SimpleNamespace:
    """The attributes guide_in_image reads, with the Estimate's names."""
    return SimpleNamespace(
        patient_reg=SimpleNamespace(T_optical_from_image=T_optical_from_image),
        robot_reg=SimpleNamespace(T_robot_from_optical=T_robot_from_optical),
        last_state=SimpleNamespace(T_robot_from_tcp=T_robot_from_tcp),
        T_change_meas=T_change, T_bias=T_bias, rig=SimpleNamespace(T_tcp_from_guide=T_tcp_from_guide))


PLAN = SimpleNamespace(entry_mm=np.array([1.0, 2.0, 3.0]), target_mm=np.array([1.0, 2.0, -70.0]))


def _snapshot(T_image_from_guide: RigidTransform | None, T_optical_from_image: RigidTransform | None,
              T_change: RigidTransform | None, tracker: dict[str, object]) -> ControllerSnapshot:
    return ControllerSnapshot(
        t_ns=12_000_000_000, t_s=12.0, state="compensate", sub_state="tracking", pending=None,
        pending_reason="", last_reason="gate open", started=True, timeline=(), fre_mm=0.1,
        tre_expected_mm=0.2, robot_fre_mm=0.05, T_optical_from_image=T_optical_from_image,
        T_robot_from_optical=None, T_bias=RigidTransform.identity(), T_change_meas=T_change,
        T_image_from_guide=T_image_from_guide, reference_optical_mm=None, live_mm=None, flange_mm=None,
        gate_deviation_mm=None, guide_error_mm=None, robot=None, tracker=tracker)  # type: ignore[arg-type]


def test_guide_in_image_follows_the_moving_patient() -> None:
    """Place the robot so that the guide sits at a known image point on the patient *after*
    the patient moved by T_change (and with a robot bias): GuideToImage must give that point."""
    T_oi = RigidTransform.from_rotvec([np.pi, 0.0, 0.0], [60.0, 0.0, 1000.0])
    T_ro = RigidTransform.from_rotvec([0.2, -0.1, 3.0], [-50.0, 300.0, 1100.0])
    T_change = RigidTransform.from_rotvec([0.01, 0.02, -0.01], [1.0, -2.0, 4.0])
    T_bias = RigidTransform.from_rotvec([0.0, 0.0, 0.002], [0.3, -0.2, 0.1])
    T_tg = RigidTransform.from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0, 60.0])
    T_image_from_guide_wanted = RigidTransform.from_rotvec([0.3, 0.1, 0.0], [5.0, -10.0, 30.0])
    # where the robot must be (robot frame) for the guide to be there, seen by the camera
    T_optical_from_guide = T_change @ T_oi @ T_image_from_guide_wanted
    T_robot_from_tcp = T_bias @ T_ro @ T_optical_from_guide @ T_tg.inverse()
    est = _fake_estimate(T_oi, T_ro, T_change, T_bias, T_robot_from_tcp, T_tg)
    got = guide_in_image(est)  # type: ignore[arg-type]
    assert got is not None
    np.testing.assert_allclose(got.as_matrix(), T_image_from_guide_wanted.as_matrix(), atol=1e-9)
    ref = RigidTransform.from_rotvec([0.1, 0.2, 0.3], [5.0, 6.0, 7.0])
    sensors = {"reference": SimpleNamespace(missing=False, T_tracker_from_sensor=ref),
               "needle": SimpleNamespace(missing=True, T_tracker_from_sensor=None)}
    snap = igtl_snapshot(_snapshot(got, T_oi, T_change, sensors), PLAN)  # type: ignore[arg-type]
    assert sorted(snap.transforms) == ["GuideToImage", "ImageToOptical", "PatientToOptical",
                                       "ReferenceToTracker"]
    np.testing.assert_allclose(snap.transforms["GuideToImage"], T_image_from_guide_wanted.as_matrix(),
                               atol=1e-9)
    np.testing.assert_allclose(snap.transforms["PatientToOptical"], (T_change @ T_oi).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(snap.transforms["ReferenceToTracker"], ref.as_matrix())
    assert snap.status == "state=compensate reason=gate open"
    np.testing.assert_array_equal(snap.points["target"], [1.0, 2.0, -70.0])


def test_deformation_string_per_marker() -> None:
    """The Deformation STRING carries the estimator, the fits' residuals and every marker's
    deviation and residual, in marker order, '-' for an unseen marker; nothing before registration."""
    T_oi = RigidTransform.from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0, 1000.0])
    base = _snapshot(None, T_oi, None, {})
    snap = dataclasses.replace(base, change_estimator="local-tps", change_fre_mm=0.4321, gate_shape_mm=0.2,
                               marker_deviations_mm=np.array([1.0, np.nan, 2.345]),
                               marker_residuals_mm=np.array([0.1, np.nan, 0.3]))
    text = igtl_snapshot(snap, PLAN).deformation  # type: ignore[arg-type]
    assert text == ("estimator=local-tps change_fre_mm=0.43 shape_mm=0.20 deviations_mm=1.00,-,2.35 "
                    "residuals_mm=0.10,-,0.30 target_model=rigid target_shift_mm=- target_turn_deg=-")
    assert igtl_snapshot(base, PLAN).deformation == ("estimator=- change_fre_mm=- shape_mm=- "  # type: ignore[arg-type]
                                                     "deviations_mm=- residuals_mm=- target_model=rigid "
                                                     "target_shift_mm=- target_turn_deg=-")
    steered = dataclasses.replace(base, target_model="surrogate", target_shift_mm=6.125, target_turn_deg=2.5,
                                  target_fallback="")
    assert igtl_snapshot(steered, PLAN).deformation.endswith(  # type: ignore[arg-type]
        "target_model=surrogate target_shift_mm=6.12 target_turn_deg=2.50")
    kept = dataclasses.replace(steered, target_fallback="the markers do not move as in the 4D CT")
    assert igtl_snapshot(kept, PLAN).deformation.endswith(  # type: ignore[arg-type]
        "target_model=surrogate target_shift_mm=- target_turn_deg=-")
    assert igtl_snapshot(dataclasses.replace(base, T_optical_from_image=None), PLAN).deformation == ""  # type: ignore[arg-type]


def test_deformation_string_on_the_wire(server: IgtlServer, client: pyigtl.OpenIGTLinkClient) -> None:
    snap = IgtlSnapshot({}, "state=gate", {}, "estimator=rigid change_fre_mm=0.50 shape_mm=0.30 "
                        "deviations_mm=1.00,2.00 residuals_mm=0.10,0.20")
    assert server.publish(snap, force=True) == 2          # status + deformation
    msg = client.wait_for_message("Deformation", timeout=DEADLINE_S)
    assert msg is not None
    assert msg.string == snap.deformation
    assert server.publish(IgtlSnapshot({}, "state=idle", {}), force=True) == 1   # none before registration


def test_nothing_before_registration() -> None:
    est = _fake_estimate(*(RigidTransform.identity(),) * 6)
    est.patient_reg = None
    assert guide_in_image(est) is None  # type: ignore[arg-type]
    assert igtl_snapshot(_snapshot(None, None, None, {}), PLAN).transforms == {}  # type: ignore[arg-type]
