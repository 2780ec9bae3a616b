"""The servo loop in its own process, with the simulated robot (and the real ur_rtde driver where
its transport is named): start-up and its report, tracking and stop through the supervisor's
robot, and the arm stopped and the process gone on every way out (close, the child killed, the
parent killed, a robot that cannot be opened)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces.errors import DisconnectedError, LifecycleError
from hil.config import default_setup_path, load_setup
from hil.geometry.transform import RigidTransform
from hil.servo.client import EV_PROCESS_RESTARTED, ServoRobot
from hil.servo.process import ServoProcess, ServoSpec
from hil.servo.shm import Stat

ROOT = Path(__file__).resolve().parents[2]


#: the correction's limits about a pivot 90 mm down the TCP's z axis (the entry)
LIMITS = (60.0, 400.0, 0.5, 2.0, (0.0, 0.0, 90.0))


def _spec(realtime: bool = False) -> ServoSpec:
    return ServoSpec(load_setup(default_setup_path()), LIMITS, realtime=realtime)


def _wait(cond: Callable[[], bool], what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


@pytest.fixture
def robot() -> Iterator[ServoRobot]:
    r = ServoRobot(ServoProcess(_spec(), "robot", RigidTransform.identity()), load_setup(
        default_setup_path()).safety.motion_limits())
    r.open()
    try:
        yield r
    finally:
        r.close()


def test_start_reports_the_robot_and_what_the_os_granted(robot: ServoRobot) -> None:
    link = robot.link
    assert isinstance(link, ServoProcess)
    assert link.ready is not None
    assert robot.control_rate_hz == 125.0           # configs/sim.toml's simulated UR3
    assert robot.rt is not None
    assert robot.rt.requested is False
    # the child's loop supervises with the simulated arm's own lag and the UR bounds
    f = robot.following_model
    assert (f.time_constant_s, f.max_error_mm, f.max_error_deg, f.max_duration_s) == (0.03, 2.0, 1.5, 0.1)
    assert f.source == "simulated arm, servo lag 0.03 s"
    _wait(lambda: link.regions.stats.get(Stat.PERIODS) > 10, "the loop to run")
    st = robot.state_now()
    assert st.t_ns > 0
    assert np.isfinite(st.T_robot_from_tcp.t).all()


def test_tracking_moves_the_arm_and_stop_is_delivered(robot: ServoRobot) -> None:
    link = robot.link
    assert isinstance(link, ServoProcess)
    start = robot.state_now().T_robot_from_tcp
    now = time.monotonic_ns()
    target = RigidTransform(start.R, start.t + np.array([0.0, 0.0, 5.0]))
    robot.start_tracking()
    robot.track(target, np.zeros(3), np.zeros(3), t_ref_ns=now, valid_until_ns=now + 5_000_000_000,
                exposure_t_ns=now, frame_seq=1, speed_scale=1.0, max_horizon_s=0.0, lead_s=0.0)
    _wait(lambda: float(np.linalg.norm(robot.state_now().T_robot_from_tcp.t - target.t)) < 0.05,
          "the arm to reach the setpoint")
    assert link.regions.stats.get(Stat.COMMANDS) > 0
    robot.stop()
    assert link.regions.stats.get(Stat.STOP_ACK_ID) == 1
    assert len(robot.stop_latency_ns) == 1
    assert robot.stop_latency_ns[0] >= 0


def test_close_stops_the_arm_and_ends_the_process() -> None:
    proc = ServoProcess(_spec(), "robot", RigidTransform.identity())
    proc.start()
    proc.close()
    assert proc.exitcode == 0
    proc.close()   # idempotent


def test_a_channel_that_ends_before_the_exit_reports_the_exit_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """The channel closes as the child dies, a moment before the OS reports its exit: the reason
    waits for the exit code (it read "code None" when taken at once, in the operator's fault).
    The child (tests/childproc/scripted_child.py) exits 0.3 s after closing its channel; the wait
    is made long here so that a loaded machine cannot make the test race the exit."""
    from hil.childproc import ChildProcess
    from hil.servo import process as servo_process

    monkeypatch.setattr(servo_process, "CHANNEL_END_WAIT_S", 60.0)
    proc = ServoProcess(_spec(), "robot", RigidTransform.identity())
    child = ChildProcess("tests.childproc.scripted_child", "servo process", "robot", ("close", -1, ()),
                         cwd=ROOT)
    proc._child = child
    proc._attach(child.spawn())   # a child, not started through start()
    try:
        child.send("hang_up")
        assert proc._pump(2.0, None) is None         # the channel's end
        assert proc.gone() == "servo process exited (code 3)"
    finally:
        child.close()


def test_a_killed_servo_process_makes_the_robot_disconnected(robot: ServoRobot) -> None:
    link = robot.link
    assert isinstance(link, ServoProcess)
    assert link.ready is not None
    os.kill(link.ready.pid, signal.SIGKILL)
    _wait(lambda: link.gone() is not None, "the parent to see the child gone")
    with pytest.raises(DisconnectedError, match="servo process"):
        robot.state_now()


def test_recover_starts_a_new_servo_process_in_place_of_one_that_died(robot: ServoRobot) -> None:
    """A servo process that ended on its own (here SIGKILL; in the field the robot library's crash
    on a dropped link, reference/ur-rtde.md trap 2) faults the controller at its next read, and
    recover() starts a new one that owns a freshly opened robot; the session log says so."""
    link = robot.link
    assert isinstance(link, ServoProcess)
    assert link.ready is not None
    events: list[tuple[str, dict[str, object]]] = []
    robot.on_event = lambda kind, fields: events.append((kind, fields))
    old_pid = link.ready.pid
    old_ring = link.regions.ring_region.name
    rings: list[str] = []
    link.restart_listeners.append(rings.append)
    with pytest.raises(LifecycleError, match="while the servo process runs"):
        link.restart()
    os.kill(old_pid, signal.SIGKILL)
    _wait(lambda: link.gone() is not None, "the parent to see the child gone")
    with pytest.raises(DisconnectedError, match=r"servo process exited \(code -9\)"):
        robot.state_now()
    robot.recover()
    assert link.gone() is None
    assert link.ready.pid != old_pid
    assert [(k, f) for k, f in events if k == EV_PROCESS_RESTARTED] == [
        (EV_PROCESS_RESTARTED, {"reason": "servo process exited (code -9)", "pid": link.ready.pid})]
    assert rings == [link.regions.ring_region.name]   # told once, the new loop's ring
    assert rings[0] != old_ring
    _wait(lambda: link.regions.stats.get(Stat.PERIODS) > 10, "the new loop to run")
    start = robot.state_now().T_robot_from_tcp
    target = RigidTransform(start.R, start.t + np.array([10.0, 0.0, 0.0]))
    robot.move_linear(target, 50.0, 200.0)           # the new loop commands the arm
    assert float(np.linalg.norm(robot.state_now().T_robot_from_tcp.t - target.t)) < 0.05
    new_pid = link.ready.pid
    robot.recover()                                   # a live process: the driver's own recover
    assert link.ready.pid == new_pid
    assert len([k for k, _ in events if k == EV_PROCESS_RESTARTED]) == 1
    robot.close()
    with pytest.raises(LifecycleError, match="after close"):
        link.restart()



def test_an_observer_reading_the_link_never_fails_a_restart(robot: ServoRobot) -> None:
    """A thread that only observes the arm (the simulated world follows it through a state view:
    ``gone()`` on every read) runs while recover() restarts a dead servo process. Before the
    restart held the channel lock, the observer could read the old child's closed channel between
    the swap's steps and mark the new start as crashed with the old exit code (CI: the first
    resume after a servo crash failed with 'servo process exited (code -6)', a second worked)."""
    link = robot.link
    assert isinstance(link, ServoProcess)
    for _ in range(3):
        assert link.ready is not None
        old_pid = link.ready.pid
        os.kill(old_pid, signal.SIGKILL)
        _wait(lambda: link.gone() is not None, "the parent to see the child gone")
        stop = threading.Event()
        reads: list[str | None] = []

        def observe(stop: threading.Event = stop, reads: list[str | None] = reads) -> None:
            while not stop.is_set():
                reads.append(link.gone())

        observer = threading.Thread(target=observe, name="observer")
        observer.start()
        try:
            robot.recover()
        finally:
            stop.set()
            observer.join(timeout=30.0)
        assert not observer.is_alive()
        assert link.gone() is None
        assert link.ready.pid != old_pid
        assert reads, "the observer never ran"
        # what the observer saw: the dead child's reason, then nothing wrong once the new one runs
        assert set(reads) <= {"servo process exited (code -9)", None}, set(reads)

_PARENT = textwrap.dedent("""
    import sys
    from hil.config import default_setup_path, load_setup
    from hil.geometry.transform import RigidTransform
    from hil.servo.process import ServoProcess, ServoSpec
    p = ServoProcess(ServoSpec(load_setup(default_setup_path()), (60.0, 400.0, 0.5, 2.0, (0.0, 0.0, 90.0)),
                               realtime=False),
                     "robot", RigidTransform.identity())
    ready = p.start()
    print("PID", ready.pid, flush=True)
    sys.stdin.read()   # until the test kills this process
""")


def test_the_servo_process_exits_when_its_supervisor_is_killed() -> None:
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              cwd=ROOT, text=True)
    child_pid = 0
    try:
        assert parent.stdout is not None
        line = ""
        while not line.startswith("PID "):
            line = parent.stdout.readline()
            assert line, "the parent ended before starting the servo process"
        child_pid = int(line.split()[1])
        parent.kill()
        parent.wait()

        def gone() -> bool:
            try:
                os.kill(child_pid, 0)
            except ProcessLookupError:
                return True
            # a zombie of the killed parent is reaped by init; /proc says whether it still runs
            try:
                return Path(f"/proc/{child_pid}/stat").read_text().split()[2] == "Z"
            except OSError:
                return True
        _wait(gone, "the orphaned servo process to stop the arm and exit")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if parent.stdin is not None:
            parent.stdin.close()
        if parent.stdout is not None:
            parent.stdout.close()
        if child_pid:
            with contextlib.suppress(ProcessLookupError):
                os.kill(child_pid, signal.SIGKILL)


def test_a_robot_that_cannot_be_opened_fails_the_start_with_its_own_error(tmp_path: Path) -> None:
    text = (ROOT / "configs" / "sim_ursim.toml").read_text()
    text = text.replace('host = "127.0.0.1"', 'host = "127.0.0.9"')   # loopback, nothing listening
    text = text.replace('stereo = "calibration/sim_stereo.json"',
                        f'stereo = "{ROOT / "configs" / "calibration" / "sim_stereo.json"}"', 1)
    cfg = tmp_path / "u.toml"
    cfg.write_text(text)
    proc = ServoProcess(ServoSpec(load_setup(cfg), LIMITS, realtime=False), "robot",
                        RigidTransform.identity())
    with pytest.raises(DisconnectedError, match=r"127\.0\.0\.9"):
        proc.start()
    assert proc.exitcode is not None   # reaped


def test_a_blocking_move_returns_with_the_arm_at_rest_on_the_target(robot: ServoRobot) -> None:
    start = robot.state_now().T_robot_from_tcp
    target = RigidTransform(start.R, start.t + np.array([10.0, 0.0, 0.0]))
    robot.move_linear(target, 50.0, 200.0)   # blocking: the loop streams it, the ring says at rest
    st = robot.state_now()
    assert robot.link.regions.stats.get(Stat.MOVE_DONE_ID) >= 1   # streamed by the loop, not a moveL
    assert float(np.linalg.norm(st.T_robot_from_tcp.t - target.t)) < 0.5
    assert st.tcp_speed_mm_s < 0.5


def test_real_time_pins_the_loop_to_the_last_cpu_and_reports_what_was_granted() -> None:
    before = os.sched_getaffinity(0)
    proc = ServoProcess(_spec(realtime=True), "robot", RigidTransform.identity())
    try:
        ready = proc.start()
        rt = ready.rt
        assert rt.requested
        if rt.cpu is not None:       # granted (root here and in CI): the last CPU this process may use
            assert rt.cpu == max(before)
        else:
            assert "affinity" in rt.errors
        if rt.fifo_priority is None:
            assert "fifo" in rt.errors
        # [servo] reserve_cpu (default): the supervisor keeps off a pinned loop's CPU while it runs
        if rt.realtime and len(before) > 1:
            assert rt.cpu is not None
            assert ready.supervisor_cpus == frozenset(before - {rt.cpu})
            assert os.sched_getaffinity(0) == before - {rt.cpu}
        else:
            assert ready.supervisor_cpus is None
            assert os.sched_getaffinity(0) == before
    finally:
        proc.close()
    assert proc.exitcode == 0
    assert os.sched_getaffinity(0) == before   # given back when the loop ended


def test_without_reserve_cpu_the_supervisor_keeps_every_cpu() -> None:
    before = os.sched_getaffinity(0)
    spec = dataclasses.replace(_spec(realtime=True), reserve_cpu=False)
    proc = ServoProcess(spec, "robot", RigidTransform.identity())
    try:
        ready = proc.start()
        assert ready.rt.requested
        assert ready.supervisor_cpus is None
        assert os.sched_getaffinity(0) == before
    finally:
        proc.close()
    assert proc.exitcode == 0
