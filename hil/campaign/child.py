"""The process one campaign run executes in: ``python -m hil.campaign.child TASK_JSON RESULT_JSON``
(started by :func:`hil.campaign.task.execute_task`, never by hand).

TASK_JSON holds ``{"tier", "spec", "hook"}``; the run's result is written to RESULT_JSON (a crash
of the runner itself is written as a failed result with its traceback). No result file means the
process died. The process exits by itself when the worker that started it is gone (its parent
changed), so a killed worker leaves no run behind.
"""

from __future__ import annotations

import importlib
import json
import os
import sys
import threading
from pathlib import Path
from typing import Any

#: How often the child checks that its parent still lives (s).
PARENT_POLL_S = 1.0
#: Exit code of a child whose parent died.
EXIT_ORPHANED = 70


def _exit_when_orphaned(parent: int) -> None:
    def watch() -> None:
        while not threading.Event().wait(PARENT_POLL_S):
            if os.getppid() != parent:
                os._exit(EXIT_ORPHANED)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _call_hook(hook: str, spec: dict[str, Any], result_path: str) -> None:
    """``module:function[:argument]`` -> ``function(spec, result_path, argument or None)``."""
    module, name, *arg = hook.split(":", 2)
    getattr(importlib.import_module(module), name)(spec, result_path, arg[0] if arg else None)


def main(argv: list[str]) -> int:
    task_path, result_path = argv
    _exit_when_orphaned(os.getppid())
    payload = json.loads(Path(task_path).read_text())
    if payload.get("hook"):
        _call_hook(str(payload["hook"]), payload["spec"], result_path)
    from .pool import _worker

    if payload["tier"] == "transport":
        from .transport import TransportSpec, run_transport_one

        _worker(payload["spec"], result_path, run_transport_one, TransportSpec)
    else:
        from .runner import RunSpec, run_one

        _worker(payload["spec"], result_path, run_one, RunSpec)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
