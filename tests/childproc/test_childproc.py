"""The child-process lifecycle the servo and perception processes share (hil/childproc.py), on a
scripted child (tests/childproc/scripted_child.py): spawn and the ready handshake, a child that
dies or fails before it is ready, one that never publishes, liveness lost, the end of the channel
before the exit, ending a child that ignores the close request, close idempotent, restart."""

from __future__ import annotations

import os
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.interfaces.errors import DeviceFaultError, DeviceTimeoutError, DisconnectedError, LifecycleError
from hil.childproc import ChildProcess, run_child

ROOT = Path(__file__).resolve().parents[2]
MODULE = "tests.childproc.scripted_child"
#: generous: a slow, loaded machine still starts a child in time (never a timing assertion)
START_S = 60.0


@pytest.fixture
def make() -> Iterator[Callable[..., ChildProcess]]:
    """Children's lifecycles for the scripted child; every one closed at the end."""
    made: list[ChildProcess] = []

    def build(terminate_wait_s: float = 2.0) -> ChildProcess:
        made.append(ChildProcess(MODULE, "test process", "dev", ("close",), cwd=ROOT,
                                 terminate_wait_s=terminate_wait_s))
        return made[-1]

    yield build
    for child in made:
        child.close(timeout_s=5.0)


def _start(child: ChildProcess, mode: str, published: Callable[[], bool] = lambda: True,
           failures: list[str] | None = None) -> Any:
    """Spawn ``child`` and run the handshake with ``mode`` as the first message; the ready payload.
    ``failures`` gets one entry per ``on_failure`` call (which ends the child)."""
    conn = child.spawn()

    def receive(wait_s: float) -> Any:
        try:
            return conn.recv() if conn.poll(wait_s) else None
        except EOFError:
            child.wait_exit(wait_s)   # the channel ends as the child dies: give the exit a moment
            return None

    def on_failure() -> None:
        if failures is not None:
            failures.append(mode)
        child.end()

    def gone() -> str | None:
        return None if child.running else child.exited()

    return child.handshake(
        mode, wait_ready=lambda: child.wait_message(receive, gone, START_S, "did not answer"),
        failed=lambda payload: DeviceFaultError(payload[1], payload[2]), published=published,
        pause=lambda: child.wait_exit(0.01), unpublished="published nothing", on_failure=on_failure,
        timeout_s=START_S)


def test_spawn_waits_for_ready_and_close_ends_the_child(make: Callable[..., ChildProcess]) -> None:
    child = make()
    assert (child.started, child.running, child.pid, child.exitcode) == (False, False, None, None)
    info = _start(child, "ready")
    assert info == {"pid": child.pid, "parent": os.getpid()}
    assert (child.started, child.running, child.exitcode) == (True, True, None)
    assert child.close() is True
    assert child.exitcode == 0        # it exited on the close request, not on a signal
    assert child.conn.closed


def test_a_child_that_dies_before_ready_is_a_typed_disconnection(make: Callable[..., ChildProcess]) -> None:
    child = make()
    failures: list[str] = []
    with pytest.raises(DisconnectedError) as err:
        _start(child, "die", failures=failures)
    assert (err.value.device, err.value.message) == ("dev", "test process exited (code 5)")
    assert failures == ["die"]
    assert child.exitcode == 5
    assert child.conn.closed          # on_failure ended it: the channel is freed


def test_a_failed_answer_raises_the_callers_error_after_ending_the_child(
        make: Callable[..., ChildProcess]) -> None:
    child = make()
    failures: list[str] = []
    with pytest.raises(DeviceFaultError) as err:
        _start(child, "fail", failures=failures)
    assert str(err.value) == "dev: cannot open"
    assert failures == ["fail"]
    assert not child.running


def test_a_child_that_exits_before_its_first_output_is_a_timeout_naming_it(
        make: Callable[..., ChildProcess]) -> None:
    child = make()
    failures: list[str] = []
    with pytest.raises(DeviceTimeoutError) as err:
        _start(child, "ready_then_exit", published=lambda: False, failures=failures)
    assert (err.value.device, err.value.message) == ("dev", "published nothing")
    assert failures == ["ready_then_exit"]


def test_wait_message_times_out_with_the_given_message(make: Callable[..., ChildProcess]) -> None:
    child = make()
    with pytest.raises(DeviceTimeoutError) as err:
        child.wait_message(lambda wait_s: None, lambda: None, 0.0, "no answer within 0 s")
    assert (err.value.device, err.value.message) == ("dev", "no answer within 0 s")


def test_liveness_lost_is_seen_and_allows_a_restart(make: Callable[..., ChildProcess]) -> None:
    child = make()
    _start(child, "ready")
    with pytest.raises(LifecycleError, match=r"^dev: restart\(\) while the test process runs$"):
        child.check_restart(crashed=False)
    child.check_restart(crashed=True)   # a reported crash: the child is on its way out
    pid = child.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    assert child.wait_exit(START_S) == -signal.SIGKILL
    assert child.running is False
    assert child.exited() == f"test process exited (code {-signal.SIGKILL})"
    child.check_restart(crashed=False)


def test_the_end_of_the_channel_waits_for_the_exit_code(make: Callable[..., ChildProcess]) -> None:
    """The channel closes as the child dies, a moment before the OS reports its exit: the reason
    waits for the code (here the child exits 0.3 s after closing its channel)."""
    child = make()
    conn = child.spawn()
    child.send("hang_up")
    with pytest.raises(EOFError):
        conn.recv()
    assert child.channel_end_reason(wait_s=START_S) == "test process exited (code 3)"


def test_a_child_that_ignores_close_and_sigterm_is_killed(make: Callable[..., ChildProcess]) -> None:
    child = make(terminate_wait_s=0.2)
    _start(child, "stubborn")
    assert child.end(timeout_s=0.2) is True
    assert child.exitcode == -signal.SIGKILL
    assert child.end() is False       # once per child


def test_close_is_idempotent_and_final(make: Callable[..., ChildProcess]) -> None:
    child = make()
    assert child.close() is False     # never started: nothing to end
    assert child.close() is False
    with pytest.raises(LifecycleError, match=r"^dev: start of the test process after close\(\)$"):
        child.spawn()
    with pytest.raises(LifecycleError, match=r"^dev: restart\(\) after close\(\)$"):
        child.check_restart(crashed=True)
    assert child.started is False


def test_close_after_a_start_ends_the_child_once(make: Callable[..., ChildProcess]) -> None:
    child = make()
    _start(child, "ready")
    assert child.close() is True
    assert child.close() is False
    assert child.end() is False
    assert child.exitcode == 0
    with pytest.raises(OSError):
        child.send(("close",))        # the channel is closed
    assert child.send_quietly(("close",)) is False


def test_restart_starts_a_new_child_in_place_of_an_ended_one(make: Callable[..., ChildProcess]) -> None:
    child = make()
    first = _start(child, "ready")["pid"]
    os.kill(first, signal.SIGKILL)
    assert child.wait_exit(START_S) == -signal.SIGKILL
    with pytest.raises(LifecycleError, match="before the previous one ended"):
        child.spawn()                 # the old child's channel is still open: end it first
    assert child.end() is True
    second = _start(child, "ready")["pid"]
    assert second == child.pid
    assert second != first
    assert child.running
    assert child.close() is True
    assert child.exitcode == 0


def test_run_child_hands_the_arguments_over_and_refuses_others(capsys: pytest.CaptureFixture[str]) -> None:
    got: list[tuple[Any, ...]] = []

    def main(conn: Any, *numbers: int) -> None:
        got.append(numbers)
        conn.close()

    r, w = os.pipe()
    os.close(w)
    assert run_child([str(r), "7", "42"], "some.child", ("NOTIFY_FD",), main) == 0
    assert got == [(7, 42)]
    for argv in (["3", "4"], ["3", "x", "4"]):
        assert run_child(argv, "some.child", ("NOTIFY_FD",), main) == 2
        assert capsys.readouterr().err == ("usage: python -m some.child FD NOTIFY_FD PARENT_PID "
                                           "(started by hil, not by hand)\n")
    assert got == [(7, 42)]
