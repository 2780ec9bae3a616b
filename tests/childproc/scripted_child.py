"""A child for the lifecycle's tests (``python -m tests.childproc.scripted_child FD PARENT_PID``,
started by :class:`hil.childproc.ChildProcess`): its first message names what it does.

- ``ready``: answers ``("ready", {"pid": ...})``, then waits for ``("close",)`` and exits 0;
- ``die``: exits 5 without an answer;
- ``fail``: answers ``("failed", ("DeviceFaultError", "dev", "cannot open"))`` and exits 0;
- ``ready_then_exit``: answers ready and exits 0 at once;
- ``stubborn``: answers ready, then ignores the close request and SIGTERM (sleeps until killed);
- ``hang_up``: closes its end of the channel, then exits 3 a moment later (0.3 s).
"""

from __future__ import annotations

import os
import signal
import sys
import time
from multiprocessing.connection import Connection

from hil.childproc import run_child


def scripted_main(conn: Connection, parent_pid: int) -> None:
    mode = conn.recv()
    if mode == "die":
        os._exit(5)
    if mode == "fail":
        conn.send(("failed", ("DeviceFaultError", "dev", "cannot open")))
        return
    if mode == "hang_up":
        conn.close()
        time.sleep(0.3)
        os._exit(3)
    if mode == "stubborn":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    conn.send(("ready", {"pid": os.getpid(), "parent": parent_pid}))
    if mode == "ready_then_exit":
        return
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg == ("close",) and mode != "stubborn":
            return


if __name__ == "__main__":
    sys.exit(run_child(sys.argv[1:], "tests.childproc.scripted_child", (), scripted_main))
