"""The suite's own guard: a test that leaves a thread, a child process or a socket behind makes
the whole run fail, naming what was left and the test that started it (tests/leakcheck.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

pytest_plugins = ["pytester"]

_LEAKY = '''
import socket, subprocess, threading, time

def test_clean():
    t = threading.Thread(target=time.sleep, args=(0.01,), name="short-lived")
    t.start()
    t.join()

def test_leaks_a_thread():
    threading.Thread(target=time.sleep, args=(60,), name="forgotten-worker", daemon=True).start()

def test_leaks_a_child():
    subprocess.Popen(["sleep", "3"])  # outlives the inner run briefly, then ends

def test_leaks_a_listening_socket():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    test_leaks_a_listening_socket.keep = s
'''


def test_leftovers_fail_the_run_and_are_named(
        pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    monkeypatch.delenv("HIL_LEAKCHECK", raising=False)
    pytester.makeconftest('pytest_plugins = ["tests.leakcheck"]\n')
    pytester.makepyfile(test_leaky=_LEAKY)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    assert result.ret == pytest.ExitCode.TESTS_FAILED
    result.assert_outcomes(passed=4)
    out = result.stdout.str()
    assert "left behind by the tests" in out
    assert "thread 'forgotten-worker' (daemon=True) started by test_leaky.py::test_leaks_a_thread" in out
    # the child ended during the grace period but was never waited for: a zombie, still named
    assert "'sleep (zombie: never waited for)' started by test_leaky.py::test_leaks_a_child" in out
    assert "TCP listening on 127.0.0.1:" in out
    assert "opened by test_leaky.py::test_leaks_a_listening_socket" in out
    assert "short-lived" not in out


def test_a_clean_run_passes(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    pytester.makeconftest('pytest_plugins = ["tests.leakcheck"]\n')
    pytester.makepyfile(test_clean="def test_ok():\n    assert 1 + 1 == 2\n")
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    assert result.ret == pytest.ExitCode.OK
    assert "left behind" not in result.stdout.str()
