"""The emulator's controller model and RTDE codec, in-process (no sockets, no real time)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from emulators.ursim import protocol as proto
from emulators.ursim.controller import (
    HOME_Q,
    ControllerVersion,
    RuntimeState,
    SafetyMode,
    UrController,
)
from emulators.ursim.motion import trapezoid
from emulators.ursim.pose import matrix_to_pose
from emulators.ursim.script import RT_CMDS, parse_program
from emulators.ursim.server import Emulator, Ports
from emulators.ursim.urscript import ScriptSyntaxError, parse_program_body, parse_statement
from hypothesis import given
from hypothesis import strategies as st

PROGRAM = "def rtde_control():\n    rtde_cmd()\nend\n"


def make(version: str = "3.15") -> UrController:
    c = UrController(ControllerVersion.parse(version))
    c.load_program(PROGRAM)
    return c


def command(c: UrController, cmd: int, dbl: list[float], async_: int = 0) -> None:
    values: dict[str, object] = {"input_int_register_0": cmd, "input_int_register_1": async_}
    values.update({f"input_double_register_{i}": float(v) for i, v in enumerate(dbl)})
    c.set_inputs(values)


def run_until(c: UrController, cond: object, max_ticks: int = 5000) -> int:
    for n in range(max_ticks):
        if cond():  # type: ignore[operator]
            return n
        c.tick()
    raise AssertionError("condition not reached")


def test_version_parsing_and_rates() -> None:
    cb3 = ControllerVersion.parse("3.15")
    assert (cb3.major, cb3.minor, cb3.frequency_hz, cb3.is_cb3) == (3, 15, 125.0, True)
    es = ControllerVersion.parse("5.11")
    assert (es.major, es.frequency_hz, es.is_cb3) == (5, 500.0, False)
    assert str(ControllerVersion.parse("5.11.6.1")) == "5.11.6.1"
    with pytest.raises(ValueError, match=r"MAJOR\.MINOR"):
        ControllerVersion.parse("5")


@given(d=st.floats(0.0, 1.0), v=st.floats(0.01, 1.0), a=st.floats(0.05, 5.0), t=st.floats(0.0, 100.0))
def test_trapezoid_is_monotonic_bounded_and_ends_at_distance(d: float, v: float, a: float, t: float) -> None:
    s = trapezoid(d, v, a, t)
    assert -1e-12 <= s <= d + 1e-12
    assert trapezoid(d, v, a, t + 0.01) >= s - 1e-12
    assert trapezoid(d, v, a, 1e6) == d


def test_handshake_ready_done_clear() -> None:
    c = make()
    assert c.runtime_state is RuntimeState.PLAYING
    assert c.out_int[0] == 1  # ready
    pose = np.array(matrix_to_pose(c.tcp))
    target = pose.copy()
    target[2] += 0.05
    command(c, 3, [*target, 0.1, 0.5])
    c.tick()
    assert c.out_int[0] == 1  # busy: still "ready" until the blocking movel is done
    n = run_until(c, lambda: c.out_int[0] == 2)
    assert n * c.dt_s == pytest.approx(0.7, abs=2 * c.dt_s)  # 50 mm at 0.1 m/s, 0.5 m/s^2
    np.testing.assert_allclose(matrix_to_pose(c.tcp)[:3], target[:3], atol=1e-9)
    command(c, 0, [])
    c.tick()
    assert c.out_int[0] == 1


def test_async_move_reports_progress_then_finishes() -> None:
    c = make()
    q = HOME_Q.copy()
    q[0] += 0.3
    command(c, 1, [*q, 1.0, 2.0], async_=1)
    c.tick()
    assert c.out_int[0] == 2  # async: done at once
    assert c.out_int[2] & 32768  # running bit
    run_until(c, lambda: not c.out_int[2] & 32768)
    np.testing.assert_allclose(c.q, q, atol=1e-12)


def test_protective_stop_pauses_the_program_and_stops_the_arm() -> None:
    c = make()
    command(c, 10, [0.0, 0.0, -0.05, 0.0, 0.0, 0.0, 0.5, 0.0])  # speedL down
    for _ in range(100):
        c.tick()
    assert c.tcp_twist[2] == pytest.approx(-0.05)
    c.protective_stop()
    for _ in range(50):
        c.tick()
    assert float(np.linalg.norm(c.qd)) == 0.0
    assert c.runtime_state is RuntimeState.PAUSED
    assert c.output("safety_status_bits", "UINT32") == (1 << 2) | (1 << 10)
    assert c.unlock_protective_stop()
    assert c.safety_mode is SafetyMode.NORMAL


def test_estop_needs_release_power_and_brakes_before_a_program_runs() -> None:
    c = make()
    c.emergency_stop()
    c.tick()
    assert c.output("safety_status_bits", "UINT32") & (1 << 7)
    c.load_program(PROGRAM)
    assert c.runtime_state is RuntimeState.STOPPED
    assert not c.power_on()
    c.release()
    assert c.power_on()
    assert c.brake_release()
    c.load_program(PROGRAM)
    assert c.runtime_state is RuntimeState.PLAYING


def test_stop_script_ends_the_program() -> None:
    c = make()
    command(c, 255, [])
    c.tick()
    assert c.runtime_state is RuntimeState.STOPPED


def test_rtde_watchdog_stops_the_program_when_not_kicked() -> None:
    c = make()
    command(c, 35, [10.0])
    c.tick()
    command(c, 0, [])
    for _ in range(12):  # 96 ms: still fed (the clear above was a kick)
        c.tick()
    assert c.runtime_state is RuntimeState.PLAYING
    for _ in range(10):
        c.tick()
    assert c.runtime_state is RuntimeState.STOPPED


def test_servo_follows_with_lag_and_settles() -> None:
    c = make()
    target = np.array(matrix_to_pose(c.tcp))
    target[0] += 0.01
    command(c, 24, [*target, 0.5, 0.5, 0.008, 0.1, 300.0])
    c.tick()
    for _ in range(3):  # 24 ms after the step it is still well short (lag ~33 ms)
        c.tick()
    assert matrix_to_pose(c.tcp)[0] - (target[0] - 0.01) < 0.008
    for _ in range(200):
        c.tick()
    assert matrix_to_pose(c.tcp)[0] == pytest.approx(target[0], abs=1e-7)


def test_unreachable_movel_faults_the_program() -> None:
    c = make()
    command(c, 3, [2.0, 0.0, 0.2, 0.0, math.pi, 0.0, 0.1, 0.5])
    c.tick()
    assert c.runtime_state is RuntimeState.STOPPED
    assert "inverse kinematics" in c.last_error


def test_program_parser_reads_offset_and_move_path() -> None:
    text = ("def rtde_control():\n    global reg_offset_int = # int register offset\n24\n"
            "    def exec_move_path():\n# inject move path\n"
            "\tsignal_async_progress(0)\n\tmovel(p[0.1,0.2,0.3,0,3.14,0],a=1.2,v=0.25,r=0)\n"
            "\tmovej([0,-1.57,1.57,-1.57,-1.57,0],a=1.4,v=1.05,r=0)\n    end\n    rtde_cmd()\nend\n")
    prog = parse_program(text)
    assert prog.is_rtde_control
    assert prog.reg_offset == 24
    assert [m.name for m in prog.move_path] == ["movel", "movej"]


def test_recipe_codec_round_trip() -> None:
    r = proto.Recipe.build(3, ["input_int_register_0", "input_double_register_0", "external_force_torque"],
                       proto.INPUT_TYPES)
    assert r is not None
    payload = struct.pack(">id6d", 7, 1.5, 1, 2, 3, 4, 5, 6)
    assert r.unpack(payload) == {"input_int_register_0": 7, "input_double_register_0": 1.5,
                                 "external_force_torque": (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)}
    with pytest.raises(proto.ProtocolViolationError, match="expected 60"):
        r.unpack(payload[:-1])
    assert proto.Recipe.build(1, ["no_such_variable"], proto.OUTPUT_TYPES) is None
    assert proto.split_names(b"timestamp,actual_q,") == ["timestamp", "actual_q"]


def test_fault_channel_commands_parse_and_report() -> None:
    c = make()
    sim = Emulator(c, "127.0.0.1", Ports())
    assert sim.control_command("protective_stop") == "ok"
    assert c.safety_mode is SafetyMode.PROTECTIVE_STOP
    assert sim.control_command("release") == "ok"
    assert sim.control_command("stall on") == "ok"
    assert c.stalled
    assert sim.control_command("stall off") == "ok"
    assert not c.stalled
    assert sim.control_command("stall maybe").startswith("error stall")
    assert sim.control_command("slow_responses 40") == "ok"
    assert c.slow_responses_s == pytest.approx(0.04)
    assert sim.control_command("slow_responses -1").startswith("error")
    assert sim.control_command("frobnicate").startswith("error unknown command")
    assert sim.control_command("status").startswith('ok {"timestamp_s"')
    assert sim.control_command("home 0 0 0").startswith("error home")


def test_urscript_subset_parses_literals_and_skips_the_rest() -> None:
    sts = parse_program_body(
        "def f():\n\twrite_output_integer_register(0 +24, 1)\n"
        "\tmovel(p[0.1,0.2,0.3,0,3.14,0], a=0.5, v=0.1)\n"
        "\tmovej([0,-1.57,1.57,-1.57,-1.57,0])\n\tsleep(0.5)\n\ttextmsg(\"hi\")\n\tstopl(2)\nend\n")
    ops = [s.op for s in sts]
    assert ops == ["skip", "write_int", "movel", "movej", "sleep", "skip", "stopl", "skip"]
    assert sts[1].values == (24.0, 1.0)
    assert sts[2].is_pose
    assert (sts[2].kw("a", 0), sts[2].kw("v", 0)) == (0.5, 0.1)
    assert sts[3].kw("v", 1.05) == 1.05
    with pytest.raises(ScriptSyntaxError, match="6 values"):
        parse_statement("movel(p[0.1, 0.2])")
    with pytest.raises(ScriptSyntaxError, match="not a literal"):
        parse_statement("sleep(t)")


def test_custom_program_runs_statements_in_order_then_stops() -> None:
    c = UrController(ControllerVersion.parse("3.15"))
    q = HOME_Q.copy()
    q[5] += 0.5
    c.load_program("def f():\n  movej([{}], a=2, v=1)\n  write_output_integer_register(0, 2)\nend\n".format(
        ",".join(repr(float(x)) for x in q)))
    assert c.runtime_state is RuntimeState.PLAYING
    run_until(c, lambda: c.runtime_state is RuntimeState.STOPPED)
    np.testing.assert_allclose(c.q, q, atol=1e-12)
    assert c.out_int[0] == 2


# ----------------------------------------------------------------------------- hostile registers
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("cmd", [1, 3, 9, 10, 11, 24])
def test_non_finite_register_faults_the_program_and_leaves_the_arm(cmd: int, bad: float) -> None:
    """A real controller faults the program on a non-finite value; the emulator must not raise
    out of tick() (that would end its tick task and hang every client)."""
    c = make()
    q0 = c.q.copy()
    command(c, cmd, [0.1, bad, 0.2, 0.0, math.pi, 0.0, 0.1, 0.5, 0.0, 0.1, 300.0])
    for _ in range(5):
        c.tick()
    assert c.runtime_state is RuntimeState.STOPPED
    assert c.last_error.startswith("input_double_register_1 is not finite")
    assert np.array_equal(c.q, q0)


@pytest.mark.parametrize(("pose", "why"), [
    ([1e308, -1e308, 1e308, 0.0, math.pi, 0.0], "inverse kinematics"),
    ([0.1, 0.1, 0.2, 1.5e308, 1.5e308, 1.5e308], "rotation vector angle overflows"),
], ids=["position", "rotation"])
@pytest.mark.parametrize("cmd", [2, 3, 24])
def test_pose_beyond_float_range_faults_the_program(cmd: int, pose: list[float], why: str) -> None:
    """Finite but absurd poses (1e308 m, a rotation vector whose norm overflows) fault the program
    naming the problem: no exception out of tick() and no overflow warning."""
    c = make()
    command(c, cmd, [*pose, 0.1, 0.5, 0.0, 0.1, 300.0])
    c.tick()
    assert c.runtime_state is RuntimeState.STOPPED
    assert why in c.last_error


def test_speedj_is_limited_to_the_joint_speed_limits() -> None:
    from emulators.ursim.motion import JOINT_SPEED_LIMIT_RAD_S

    c = make()
    command(c, 9, [1e308, -1e308, 1e308, -1e308, 1e308, -1e308, 1e308])
    for _ in range(3):
        c.tick()
    assert c.runtime_state is RuntimeState.PLAYING
    assert np.allclose(np.abs(c.qd), JOINT_SPEED_LIMIT_RAD_S)


@given(st.sampled_from(sorted(RT_CMDS | {1, 2, 3, 4, 5, 7, 8, 30, 33, 34, 35, 44, 46})),
       st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=12, max_size=12))
def test_any_registers_never_break_the_tick(cmd: int, dbl: list[float]) -> None:
    c = make()
    command(c, cmd, dbl)
    for _ in range(4):
        c.tick()
    command(c, 0, [])
    c.tick()
    assert np.all(np.isfinite(c.q))
    assert np.all(np.isfinite(c.tcp))


# ------------------------------------------------------------------ RTDE inputs (registers.py)
@given(old=st.integers(0, (1 << 18) - 1), mask=st.integers(0, 255), value=st.integers(0, 255),
       which=st.sampled_from([("standard_digital_output", 0, 8), ("configurable_digital_output", 8, 8),
                              ("tool_digital_output", 16, 2)]))
def test_a_digital_output_package_changes_exactly_the_bits_in_its_mask(
        old: int, mask: int, value: int, which: tuple[str, int, int]) -> None:
    from emulators.ursim.registers import Registers

    name, shift, width = which
    regs = Registers(digital_out_bits=old)
    regs.apply({f"{name}_mask": mask, name: value})
    window = ((1 << width) - 1) << shift
    changed = (mask << shift) & window
    assert regs.digital_out_bits == (old & ~changed) | ((value << shift) & changed)


@given(mask=st.integers(0, 2**32 - 1), fraction=st.floats(-1.0, 2.0))
def test_the_speed_slider_moves_only_with_mask_1(mask: int, fraction: float) -> None:
    c = make()
    c.set_inputs({"speed_slider_mask": mask, "speed_slider_fraction": fraction})
    c.tick()  # the outputs of the next period
    expected = max(0.0, min(1.0, fraction)) if mask == 1 else 1.0
    assert c.output("target_speed_fraction", "DOUBLE") == expected


def _ursim_imports() -> dict[str, set[str]]:
    """Each module of tools/emulators/ursim -> the package's modules it imports (every form:
    ``import a.b``, ``from a.b import c``, ``from a import b``, relative; TYPE_CHECKING ones too)."""
    import ast
    from pathlib import Path

    import emulators.ursim as pkg

    root = Path(pkg.__file__).parent
    names = {p.stem for p in root.glob("*.py")}
    graph: dict[str, set[str]] = {}
    for path in root.glob("*.py"):
        found: set[str] = set()
        for n in ast.walk(ast.parse(path.read_text())):
            if isinstance(n, ast.Import):
                mods = [a.name for a in n.names]
            elif isinstance(n, ast.ImportFrom):
                base = "emulators.ursim" if n.level else (n.module or "")
                full = f"{base}.{n.module}" if n.level and n.module else base
                mods = [full, *(f"{full}.{a.name}" for a in n.names)]
            else:
                continue
            found |= {m.split(".")[2] for m in mods if m.startswith("emulators.ursim.")} & names
        graph[path.stem] = found - {path.stem}
    return graph


def _reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen: set[str] = set()
    todo = list(graph[start])
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph.get(m, ()))
    return seen


def test_the_program_interpreter_does_not_import_the_controller() -> None:
    """script.py reaches the controller only through its ScriptHost protocol (issue 45 item 4): no
    import of the controller, directly or through another module, in any form; the controller
    owns its interpreter (it imports the script, one way); no module of the emulator imports
    itself back through others."""
    import emulators.ursim.script as script

    graph = _ursim_imports()
    assert graph["controller"] >= {"script"}
    assert "controller" not in _reachable(graph, "script")
    assert [m for m in graph if m in _reachable(graph, m)] == []   # no import cycle
    host: script.ScriptHost = make()  # the controller is a ScriptHost (mypy checks the members)
    assert isinstance(host, UrController)
