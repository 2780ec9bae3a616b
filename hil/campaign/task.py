"""One campaign run as a task an executor runs on a worker (this process's thread pool, or a Dask
worker on another machine): a pure function of (scenario, seed, config digest, code version)
that returns a self-contained record.

On the worker, :func:`execute_task`:

1. checks that the worker runs the campaign's code version and sees the same config (digest of
   the files' contents) - a run on different code or config is recorded as an error, not run;
2. for a transport run, starts the run's emulator on this worker (:mod:`hil.campaign.emulators`);
3. runs the run in a child process (``python -m hil.campaign.child``, its own session), bounded
   by ``timeout_s`` of wall time: past it the child's whole process group is killed (a *hang*);
4. builds the record: the runner's result, ``inputs``, ``replay``, ``session_log_sha256``,
   ``code_version`` and ``host``; and returns the session log (and, for transport, the run
   directory) as bytes when the run failed or logs are kept, so nothing needs a shared filesystem.

A hang or a child that died without a result is marked *retryable*: the executor runs it again
once (:mod:`hil.campaign.executor`).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from hil.session.log import file_sha256

from .runner import RunResult
from .version import code_version, config_digest

Tier = Literal["simulator", "transport"]
#: Most bytes of logs a task sends back (the session log of a failing run is ~1-3 MB).
MAX_SHIPPED_BYTES = 64 * 1024 * 1024
#: Last characters of the child's stderr kept in the record of a run that died.
STDERR_TAIL_CHARS = 2000

_live: set[subprocess.Popen[bytes]] = set()  # the run processes this process started, still running
_live_lock = threading.Lock()


def kill_running() -> int:
    """Kill every run process this process started that still runs (an interrupted campaign);
    returns how many. Their tasks record them as died."""
    with _live_lock:
        procs = list(_live)
    for proc in procs:
        _kill_group(proc)
    return len(procs)


@dataclass(frozen=True)
class RunTask:
    """Everything a worker needs for one run (picklable; crosses to Dask workers).

    ``spec``: the runner's spec without ``log_dir`` (simulator: :class:`~hil.campaign.runner.RunSpec`
    fields; transport: ``scenario`` and ``seed``). ``inputs``: what the record echoes.
    ``code_version``/``config_sha256``: what the worker must match (unless ``check_version`` is
    False). ``paths``: the files the config digest is taken over, as the worker sees them.
    ``hook``: ``module:function[:argument]``, called in the child before the run as
    ``function(spec, result_path, argument)`` (tests: a run that dies, hangs, kills its worker).
    """

    tier: Tier
    run_id: str
    spec: dict[str, Any]
    inputs: dict[str, Any]
    replay: str
    timeout_s: float
    code_version: str
    config_sha256: str
    paths: tuple[str, ...]
    keep_logs: bool = False
    check_version: bool = True
    hook: str | None = None


@dataclass
class TaskOutcome:
    """What a task returns: the record, the log files to write under the campaign's ``logs/``
    (relative path -> bytes), and whether the failure was of the run's process (retryable)."""

    record: dict[str, Any]
    files: dict[str, bytes] = field(default_factory=dict)
    retryable: bool = False


def _error_record(task: RunTask, outcome: str, reasons: list[str], error: str | None = None,
                  wall_s: float | None = None) -> dict[str, Any]:
    i = task.inputs
    return RunResult(task.run_id, str(i["scenario"]), i.get("kind"), i.get("state"), int(i["seed"]),
                     passed=False, outcome=outcome, reasons=reasons, error=error, wall_s=wall_s).to_dict()


def finish_record(task: RunTask, result: dict[str, Any], *, log_sha256: str | None = None,
                  worker_version: str | None = None, host: str | None = None) -> dict[str, Any]:
    """``result`` plus the fields every record carries (``tier``, ``inputs``, ``replay``,
    ``session_log_sha256``, ``code_version``, ``host``, ``attempts`` - the executor sets it)."""
    return {**result, "tier": task.tier, "inputs": dict(task.inputs), "replay": task.replay,
            "session_log_sha256": log_sha256, "code_version": worker_version or task.code_version,
            "host": host, "attempts": 1}


def _mismatch(task: RunTask, worker_version: str) -> list[str]:
    if not task.check_version:
        return []
    reasons = []
    if worker_version != task.code_version:
        reasons.append(f"worker {socket.gethostname()} runs code {worker_version}, the campaign "
                       f"{task.code_version} (install the same commit, or --allow-mismatch)")
    try:
        digest = config_digest(task.paths)
    except OSError as exc:
        return [*reasons, f"worker {socket.gethostname()} cannot read the config: {exc}"]
    if digest != task.config_sha256:
        reasons.append(f"worker {socket.gethostname()} sees a different config "
                       f"(sha256 {digest[:12]}, the campaign {task.config_sha256[:12]}): "
                       f"{', '.join(task.paths)}")
    return reasons


def execute_task(task: RunTask) -> TaskOutcome:
    """Run one task on this worker (see the module doc). Blocking: at most ``task.timeout_s`` of
    run time, plus an emulator's start for a transport run. Never raises for a run's problem (the
    record says it); raises only for a bug of the campaign itself."""
    host = socket.gethostname()
    worker_version = str(code_version()["id"])
    wrong = _mismatch(task, worker_version)
    if wrong:
        rec = _error_record(task, "error", wrong)
        return TaskOutcome(finish_record(task, rec, worker_version=worker_version, host=host))
    tmp = Path(tempfile.mkdtemp(prefix="hil-campaign-"))
    try:
        outcome = _run_in_child(task, tmp)
        rec = outcome.record
        log = tmp / f"{task.run_id}.jsonl"
        sha = file_sha256(log) if log.is_file() else None
        outcome.record = finish_record(task, rec, log_sha256=sha, worker_version=worker_version, host=host)
        if not rec.get("passed") or task.keep_logs:
            outcome.files = _collect(tmp, task.run_id)
        return outcome
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run_in_child(task: RunTask, tmp: Path) -> TaskOutcome:
    """Prepare (transport: start the emulator here), run the child, read its result."""
    stop: Any = None
    child_spec = {**task.spec, "log_dir": str(tmp)}
    if task.tier == "transport":
        from dataclasses import asdict

        from .emulators import EmulatorError
        from .transport import BY_NAME, _prepare

        try:
            prepared = _prepare(BY_NAME[task.spec["scenario"]], int(task.spec["seed"]), tmp)
        except EmulatorError as exc:
            return TaskOutcome(_error_record(task, "crashed", [f"emulator: {exc}"]))
        child_spec, stop = asdict(prepared.spec), prepared.stop
    try:
        return _child(task, child_spec, tmp)
    finally:
        if stop is not None:
            stop()


@dataclass(frozen=True)
class ChildRun:
    """What one run in a child process left: its ``result`` (the JSON it wrote) or, without one,
    whether it ``hung`` (killed at its timeout) or its ``returncode`` and ``stderr_tail``."""

    result: dict[str, Any] | None
    hung: bool
    returncode: int | None
    stderr_tail: str | None
    wall_s: float


def run_child_module(module: str, payload: dict[str, Any], tmp: Path, timeout_s: float) -> ChildRun:
    """Run ``python -m MODULE TASK.json RESULT.json`` in its own session (``payload`` as the task
    file, in ``tmp``), at most ``timeout_s`` of wall time. A hang, or an interruption while
    waiting, kills the child's whole process group; every child is in :func:`kill_running`'s
    set while it runs. Blocking; never raises for the child's failure (the :class:`ChildRun`
    says it)."""
    task_path, result_path, err_path = tmp / "task.json", tmp / "result.json", tmp / "stderr.txt"
    task_path.write_text(json.dumps(payload))
    t0 = time.monotonic()
    with open(err_path, "wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", module, str(task_path), str(result_path)],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True,
        )
        with _live_lock:
            _live.add(proc)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _kill_group(proc)
            return ChildRun(None, True, None, None, round(time.monotonic() - t0, 3))
        finally:
            if proc.poll() is None:  # interrupted while waiting: leave nothing behind
                _kill_group(proc)
            with _live_lock:
                _live.discard(proc)
    wall_s = round(time.monotonic() - t0, 3)
    if result_path.is_file():
        return ChildRun(json.loads(result_path.read_text()), False, proc.returncode, None, wall_s)
    tail = err_path.read_text(errors="replace")[-STDERR_TAIL_CHARS:] or None
    return ChildRun(None, False, proc.returncode, tail, wall_s)


def _child(task: RunTask, child_spec: dict[str, Any], tmp: Path) -> TaskOutcome:
    run = run_child_module("hil.campaign.child", {"tier": task.tier, "spec": child_spec, "hook": task.hook},
                           tmp, task.timeout_s)
    if run.result is not None:
        return TaskOutcome(run.result)
    if run.hung:
        reasons = [f"run did not finish within {task.timeout_s:.0f} s (hang)"]
        return TaskOutcome(_error_record(task, "hang", reasons, wall_s=run.wall_s), retryable=True)
    reasons = [f"run process died (exit code {run.returncode})"]
    return TaskOutcome(_error_record(task, "crashed", reasons, error=run.stderr_tail), retryable=True)


def _kill_group(proc: subprocess.Popen[bytes]) -> None:
    """SIGKILL the child's process group (the run and anything it started), then reap the child."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=10.0)


def _collect(tmp: Path, run_id: str) -> dict[str, bytes]:
    """The run's files (``<run_id>.jsonl``, its ``.head``, a transport run's directory), up to
    :data:`MAX_SHIPPED_BYTES` in all (the largest beyond that are left out)."""
    own = {run_id, f"{run_id}.jsonl", f"{run_id}.jsonl.head"}
    files = sorted((p for p in tmp.rglob("*") if p.is_file() and p.relative_to(tmp).parts[0] in own),
                   key=lambda p: p.stat().st_size)
    out: dict[str, bytes] = {}
    total = 0
    for p in files:
        size = p.stat().st_size
        if total + size > MAX_SHIPPED_BYTES:
            continue
        out[p.relative_to(tmp).as_posix()] = p.read_bytes()
        total += size
    return out
