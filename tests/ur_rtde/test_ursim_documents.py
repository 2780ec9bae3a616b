"""The emulator against Universal Robots' published documents, checked from a client's side over
loopback: the real ur-rtde library where it has the call, raw sockets written from the documents
(tests/ur_rtde/ur_wire.py) elsewhere.

- RTDE guide: input registers are outputs too; an input variable another client writes is IN_USE;
  ``standard/configurable/tool_digital_output`` under their masks land in
  ``actual_digital_output_bits``; ``speed_slider_mask`` = 0 leaves the slider alone.
- Dashboard command list: ``get operational mode`` (5.x only).
- Client interfaces page: realtime packets on 30003; version and robot state messages on 30001/30002.
"""

from __future__ import annotations

import math
import socket

import pytest
import rtde_io
import rtde_receive
from dashboard_client import DashboardClient

from tests.ur_rtde.conftest import Ursim, wait_for
from tests.ur_rtde.ur_wire import (
    RawRtde,
    parse_robot_state,
    parse_version_message,
    read_primary_message,
    read_realtime,
)

HOME_Q = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)


# ------------------------------------------------------------------------------ RTDE guide
def test_input_registers_are_read_back_as_outputs_by_another_client(ursim: Ursim) -> None:
    names = ["input_int_register_40", "input_double_register_40", "input_bit_register_70",
             "input_bit_registers32_to_63"]
    with RawRtde(ursim.host) as writer, RawRtde(ursim.host) as reader:
        rid, types = writer.setup_inputs(names)
        assert (rid, types) == (1, ["INT32", "DOUBLE", "BOOL", "UINT32"])
        rid_out, out_types = reader.setup_outputs(names)
        assert rid_out != 0
        assert out_types == ["INT32", "DOUBLE", "BOOL", "UINT32"]
        reader.start()
        writer.send_inputs(rid, types, [-123456, 2.5, True, 0x80000001])
        out = reader.wait_outputs(lambda o: o["input_int_register_40"] == -123456, what="register echo")
        assert out == {"input_int_register_40": -123456, "input_double_register_40": 2.5,
                       "input_bit_register_70": True, "input_bit_registers32_to_63": 0x80000001}
        writer.send_inputs(rid, types, [0, 0.0, False, 0])
        reader.wait_outputs(lambda o: o == dict.fromkeys(names, 0), what="registers cleared")


def test_a_second_clients_input_recipe_on_a_register_in_use_is_refused_with_in_use(ursim: Ursim) -> None:
    with RawRtde(ursim.host) as first:
        assert first.setup_inputs(["input_int_register_41"]) == (1, ["INT32"])
        assert first.setup_inputs(["input_int_register_41", "input_double_register_41"])[0] == 2
        with RawRtde(ursim.host) as second:
            assert second.setup_inputs(["input_double_register_42", "input_int_register_41"]) == (
                0, ["DOUBLE", "IN_USE"])
    with RawRtde(ursim.host) as third:  # the first client is gone: the register is free again
        assert third.setup_inputs(["input_double_register_42", "input_int_register_41"]) == (
            1, ["DOUBLE", "INT32"])


def test_ur_rtde_refuses_a_second_io_interface_whose_registers_are_in_use(
        ursim: Ursim, capfd: pytest.CaptureFixture[str]) -> None:
    io = rtde_io.RTDEIOInterface(ursim.host)
    try:
        with pytest.raises(RuntimeError, match="already in use"):
            rtde_io.RTDEIOInterface(ursim.host)
    finally:
        io.disconnect()
    io = rtde_io.RTDEIOInterface(ursim.host)  # after the first disconnected, a new one is accepted
    io.disconnect()
    capfd.readouterr()


def test_digital_outputs_set_under_their_masks_are_reflected_in_actual_digital_output_bits(
        ursim: Ursim, capfd: pytest.CaptureFixture[str]) -> None:
    io = rtde_io.RTDEIOInterface(ursim.host)
    receive = rtde_receive.RTDEReceiveInterface(ursim.host)
    try:
        io.setStandardDigitalOut(3, True)
        io.setConfigurableDigitalOut(2, True)
        io.setToolDigitalOut(1, True)
        expected = (1 << 3) | (1 << (8 + 2)) | (1 << (16 + 1))
        wait_for(lambda: receive.getActualDigitalOutputBits() == expected, what="output bits set")
        assert receive.getDigitalOutState(3)
        assert not receive.getDigitalOutState(2)
        io.setStandardDigitalOut(3, False)  # only bit 3 is in the mask: the others stay
        wait_for(lambda: receive.getActualDigitalOutputBits() == expected & ~(1 << 3), what="bit 3 cleared")
    finally:
        io.setConfigurableDigitalOut(2, False)
        io.setToolDigitalOut(1, False)
        wait_for(lambda: receive.getActualDigitalOutputBits() == 0, what="outputs cleared")
        io.disconnect()
        receive.disconnect()
    capfd.readouterr()


def test_speed_slider_mask_zero_leaves_the_speed_slider_alone(ursim: Ursim) -> None:
    inputs = ["speed_slider_mask", "speed_slider_fraction", "input_int_register_44"]
    outputs = ["speed_scaling", "target_speed_fraction", "input_int_register_44"]
    with RawRtde(ursim.host) as writer, RawRtde(ursim.host) as reader:
        rid, types = writer.setup_inputs(inputs)
        assert types == ["UINT32", "DOUBLE", "INT32"]
        reader.setup_outputs(outputs)
        reader.start()

        def send(mask: int, fraction: float, seq: int) -> dict[str, object]:
            writer.send_inputs(rid, types, [mask, fraction, seq])  # the register marks it applied
            return reader.wait_outputs(lambda o: o["input_int_register_44"] == seq, what=f"package {seq}")

        assert send(0, 0.0, 1) == {"speed_scaling": 1.0, "target_speed_fraction": 1.0,
                                   "input_int_register_44": 1}
        assert send(1, 0.25, 2)["target_speed_fraction"] == 0.25
        assert send(0, 0.9, 3)["target_speed_fraction"] == 0.25
        assert send(1, 1.0, 4)["target_speed_fraction"] == 1.0


# ---------------------------------------------------------------------- dashboard command list
@pytest.mark.parametrize(("fixture", "answer"), [
    ("ursim_e_series", "NONE"),
    ("ursim", "could not understand: 'get operational mode'"),
])
def test_get_operational_mode_is_answered_on_e_series_and_unknown_on_cb3(
        fixture: str, answer: str, request: pytest.FixtureRequest,
        capfd: pytest.CaptureFixture[str]) -> None:
    sim: Ursim = request.getfixturevalue(fixture)
    dash = DashboardClient(sim.host)
    dash.connect()
    try:
        dash.send("get operational mode\n")
        assert dash.receive().strip() == answer
    finally:
        dash.disconnect()
    capfd.readouterr()


# ------------------------------------------------------------------ client interfaces page
@pytest.mark.parametrize(("fixture", "period_s"), [("ursim", 1 / 125), ("ursim_e_series", 1 / 500)])
def test_realtime_interface_streams_the_documented_packet_every_controller_period(
        fixture: str, period_s: float, request: pytest.FixtureRequest) -> None:
    sim: Ursim = request.getfixturevalue(fixture)
    status = sim.control.status()
    with socket.create_connection((sim.host, 30003), timeout=5.0) as s:
        size, first = read_realtime(s)
        _, second = read_realtime(s)
        assert size == 1220
        assert second["time"] - first["time"] == pytest.approx(period_s, abs=1e-9)
        assert second["q_actual"] == HOME_Q
        assert second["q_target"] == HOME_Q
        assert second["qd_actual"] == (0.0,) * 6
        assert second["tool_vector_actual"] == pytest.approx(status["tcp_pose"], abs=1e-9)
        assert (second["robot_mode"], second["safety_mode"], second["safety_status"]) == (7.0, 1.0, 1.0)
        assert (second["program_state"], second["speed_scaling"]) == (1.0, 1.0)  # STOPPED, 100 %
        assert second["joint_modes"] == (253.0,) * 6
        sim.control.protective_stop()
        while second["safety_mode"] != 3.0:  # bounded by the socket timeout
            _, second = read_realtime(s)
        assert second["safety_status"] == 3.0


@pytest.mark.parametrize(("fixture", "port", "version", "e_series"), [
    ("ursim", 30001, (3, 15, 7, 106331), False),
    ("ursim", 30002, (3, 15, 7, 106331), False),
    ("ursim_e_series", 30002, (5, 11, 6, 108663), True),
])
def test_primary_and_secondary_send_the_version_then_robot_state_at_10_hz(
        fixture: str, port: int, version: tuple[int, ...], e_series: bool,
        request: pytest.FixtureRequest) -> None:
    sim: Ursim = request.getfixturevalue(fixture)
    status = sim.control.status()
    with socket.create_connection((sim.host, port), timeout=5.0) as s:
        typ, msg = read_primary_message(s)
        assert typ == 20
        v = parse_version_message(msg)
        assert (v["project"], v["version"]) == ("URControl", version)
        states = []
        while len(states) < 2:
            typ, msg = read_primary_message(s)
            if typ == 16:
                states.append(parse_robot_state(msg, e_series))
    mode, joints, cart = states[1][0], states[1][1], states[1][4]
    assert mode["size"] == (47 if e_series else 46)
    assert joints["size"] == 251
    assert cart["size"] == 101
    assert (mode["connected"], mode["power_on"], mode["emergency_stopped"],
            mode["protective_stopped"], mode["program_running"], mode["robot_mode"]) == (
        True, True, False, False, False, 7)
    assert joints["q_actual"] == HOME_Q
    assert joints["joint_mode"] == (253,) * 6
    assert cart["tcp"] == pytest.approx(status["tcp_pose"], abs=1e-9)
    dt_us = states[1][0]["timestamp"] - states[0][0]["timestamp"]
    assert 95_000 <= dt_us <= 100_001  # 10 Hz: every 12 periods at 125 Hz (96 ms), 50 at 500 Hz


def test_a_realtime_client_that_sends_a_program_is_no_longer_streamed_to(ursim: Ursim) -> None:
    """Our deviation (docs/ursim.md): a 30003 client that sends a program is a script client."""
    with socket.create_connection((ursim.host, 30003), timeout=5.0) as s:
        assert read_realtime(s)[0] == 1220
        assert ursim.control.status()["realtime_clients"] == 1
        s.sendall(b"write_output_integer_register(46, 0)\n")
        wait_for(lambda: ursim.control.status()["realtime_clients"] == 0, what="stream stopped")


def test_a_script_line_sent_on_the_primary_interface_runs(ursim: Ursim) -> None:
    with RawRtde(ursim.host) as reader, socket.create_connection((ursim.host, 30001), timeout=5.0) as s:
        reader.setup_outputs(["output_int_register_45"])
        reader.start()
        s.sendall(b"write_output_integer_register(45, 77)\n")
        reader.wait_outputs(lambda o: o["output_int_register_45"] == 77, what="register written")
        s.sendall(b"write_output_integer_register(45, 0)\n")
        reader.wait_outputs(lambda o: o["output_int_register_45"] == 0, what="register cleared")

