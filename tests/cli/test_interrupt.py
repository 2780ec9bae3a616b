"""``hil run`` on the wall clock (the servo loop in its own process) ended by Ctrl-C or SIGTERM:
the command unwinds, ends the servo process (which stops the arm on close: tests/servo), closes
the session log saying how and in which state it ended, and exits 130 (interrupted) or 143
(terminated) with one line on stderr — nothing left running, nothing left in /dev/shm."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(x) for x in text.split()]


def _wait(cond: Callable[[], bool], what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _unmapped(names: set[str]) -> set[str]:
    """The shared-memory files no process maps (left behind): other test runs on this machine may
    have live ones of their own."""
    mapped: set[str] = set()
    for maps in Path("/proc").glob("[0-9]*/maps"):
        try:
            text = maps.read_text(errors="replace")
        except OSError:
            continue
        mapped |= {n for n in names if f"/dev/shm/{n}" in text}
    return names - mapped


def _config(tmp_path: Path) -> Path:
    text = (ROOT / "configs" / "sim.toml").read_text()
    text = text.replace("real_time = false", "real_time = true")
    text = text.replace('stereo = "calibration/sim_stereo.json"',
                        f'stereo = "{ROOT / "configs" / "calibration" / "sim_stereo.json"}"')
    cfg = tmp_path / "sim_rt.toml"
    cfg.write_text(text)
    return cfg


@pytest.mark.slow
@pytest.mark.parametrize(("sig", "code", "word"), [(signal.SIGINT, 130, "interrupted"),
                                                   (signal.SIGTERM, 143, "terminated")])
def test_hil_run_ended_by_a_signal_closes_everything(tmp_path: Path, sig: int, code: int, word: str) -> None:
    sessions = tmp_path / "sessions"
    shm_before = set(os.listdir("/dev/shm"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil", "run", str(_config(tmp_path)), "--auto", "--no-report",
         "--plan", str(ROOT / "configs" / "plans" / "sim_plan.json"), "--session-dir", str(sessions)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # a test runner started in the background may ignore SIGINT: give the child the default
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    servo: list[int] = []
    try:
        def servo_running() -> bool:
            servo[:] = [c for c in _children(proc.pid)
                        if "hil.servo.child" in Path(f"/proc/{c}/cmdline").read_text(errors="replace")]
            return bool(servo) and any(sessions.glob("session_*.jsonl"))

        _wait(servo_running, "the servo process and the session log")
        log = next(sessions.glob("session_*.jsonl"))
        _wait(lambda: '"state_entered"' in log.read_text(), "the procedure to start")
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == code, err[-2000:]
    assert err.strip().splitlines()[-1] == f"hil run: {word}"
    assert "Traceback" not in err
    _wait(lambda: not Path(f"/proc/{servo[0]}").exists(), "the servo process to end", 10.0)
    assert _unmapped(set(os.listdir("/dev/shm")) - shm_before) == set()
    records = [json.loads(line) for line in log.read_text().splitlines()]
    closed = records[-1]
    assert closed["event"] == "session_closed"
    assert (closed["final_state"], closed["ended_by"]) == (
        "interrupted", "TerminatedError" if sig == signal.SIGTERM else "KeyboardInterrupt")
    assert closed["state"] in ("idle", "register", "plan", "approach", "gate", "compensate")
