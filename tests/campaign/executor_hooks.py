"""Hooks the executor tests put in a run's child process (``RunTask.hook``): called before the
run as ``hook(spec, result_path, argument)``. Each one stands for a failure of the run's
infrastructure, not of the controller; ``argument`` is a directory for the once-only markers.

Deliberately light: no ``hil`` import, so a child that only runs a hook starts in a fraction of a
second.
"""

from __future__ import annotations

import json
import os
import signal
import threading
from pathlib import Path
from typing import Any


def _first_time(spec: dict[str, Any], marker_dir: str | None) -> bool:
    """True the first time for this run id (creates its marker atomically)."""
    assert marker_dir is not None
    try:
        fd = os.open(Path(marker_dir) / f"{spec['run_id']}.once", os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    os.close(fd)
    return True


def passes(spec: dict[str, Any], result_path: str, _arg: str | None = None) -> None:
    """Write a passing result for ``spec`` and exit (no simulation)."""
    result = {"run_id": spec["run_id"], "scenario": "baseline" if spec.get("kind") is None else
              f"{spec['kind']}@{spec['state']}", "kind": spec.get("kind"), "state": spec.get("state"),
              "seed": spec["seed"], "passed": True, "reasons": [], "outcome": "baseline"}
    Path(result_path).write_text(json.dumps(result))
    os._exit(0)


def dies_once(spec: dict[str, Any], result_path: str, marker_dir: str | None) -> None:
    """The run's process is killed (SIGKILL) the first time; passes the second."""
    if _first_time(spec, marker_dir):
        os.kill(os.getpid(), signal.SIGKILL)
    passes(spec, result_path)


def dies_always(spec: dict[str, Any], result_path: str, _arg: str | None = None) -> None:
    """The run's process is killed (SIGKILL) every time."""
    os.kill(os.getpid(), signal.SIGKILL)


def hangs(spec: dict[str, Any], result_path: str, _arg: str | None = None) -> None:
    """The run never finishes (until its bound kills it)."""
    threading.Event().wait()


def kills_worker_once(spec: dict[str, Any], result_path: str, marker_dir: str | None) -> None:
    """The first time, kill the worker that started this run (the child's parent: a Dask worker
    process) and die with it; passes the second time."""
    if _first_time(spec, marker_dir):
        os.kill(os.getppid(), signal.SIGKILL)
        os.kill(os.getpid(), signal.SIGKILL)
    passes(spec, result_path)
