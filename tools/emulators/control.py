"""The emulators' control interface transport: a Unix stream socket, one command line in, one
answer line out (``ok ...`` / ``error: ...``), served on a daemon thread."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable
from pathlib import Path


def serve_control_lines(path: Path, answer: Callable[[str], str], stop: threading.Event,
                        name: str = "control") -> socket.socket:
    """Listen on the Unix socket ``path`` (replacing a stale one); for every line a client sends,
    write back ``answer(line)`` and a newline. Runs until ``stop`` is set or the returned socket is
    closed. Clients may come and go; a client vanishing mid-line is ignored."""
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(4)
    srv.settimeout(0.2)

    def loop() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn, conn.makefile("rw", encoding="utf-8", newline="\n") as f:
                try:
                    for line in f:
                        f.write(answer(line) + "\n")
                        f.flush()
                except OSError:
                    continue

    threading.Thread(target=loop, name=name, daemon=True).start()
    return srv
