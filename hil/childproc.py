"""One child interpreter's lifecycle, shared by the servo process (:mod:`hil.servo.process`) and
the perception process (:mod:`hil.perception.process`): spawn, the ready handshake, liveness,
close, and restart (a new child in place of one that ended).

The child is ``python -m MODULE FD [EXTRA_FD ...] PARENT_PID``: a fresh interpreter, so nothing
of the parent's threads, locks or heap comes along and the caller's main module is never re-run.
FD is its end of the channel (a socket pair with :class:`multiprocessing.connection.Connection`
framing), the extra file descriptors are passed on in order (the perception process's
notification pipe), and PARENT_PID lets the child notice that its parent is gone. The child's
entry module hands its arguments to :func:`run_child`.

What goes over the channel belongs to each process; the lifecycle knows three messages: the
parent's first one (the spec), the child's answer to it, ``("ready", payload)`` or
``("failed", payload)`` (:meth:`ChildProcess.handshake`), and the close request, given to
:class:`ChildProcess` as ``close_message``.

Ending a child (:meth:`ChildProcess.end`: close, a failed start, before a restart): send it the
close request and wait up to ``timeout_s`` for its exit, then terminate it (SIGTERM) and wait
``terminate_wait_s``, then kill it (SIGKILL) and reap it; then close the channel. Once per child,
never raises. A restart is :meth:`~ChildProcess.end` (the old child) then
:meth:`~ChildProcess.spawn` again (:meth:`~ChildProcess.check_restart` says whether it may).

Blocking: :meth:`~ChildProcess.spawn` returns once the interpreter is started (not ready);
:meth:`~ChildProcess.handshake` blocks until the child is ready, within the given timeouts;
:meth:`~ChildProcess.end` up to ``timeout_s`` + ``terminate_wait_s``. Thread safety: sends are
serialised (:meth:`~ChildProcess.send`); spawning and ending are the owner's, one thread at a time.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError, LifecycleError

#: How long a child may take to start, s (a fresh interpreter importing numpy and a driver).
START_TIMEOUT_S = 60.0
#: How long the end of the channel waits for the child's exit to be reported, s.
CHANNEL_END_WAIT_S = 1.0
#: How long an ending child gets after SIGTERM before SIGKILL, s.
TERMINATE_WAIT_S = 2.0


class ChildProcess:
    """The parent's side of one child process at a time (module doc).

    Args:
        module: the child's entry module (``python -m module FD [EXTRA_FD ...] PARENT_PID``).
        label: what the errors and reasons call the process ("servo process").
        device: the device name the errors raised here carry (the robot's, the camera's).
        close_message: the message that asks the child to stop and exit.
        cwd: the child's working directory (None: this process's).
        terminate_wait_s: how long an ending child gets after SIGTERM before SIGKILL, s.
    """

    def __init__(self, module: str, label: str, device: str, close_message: tuple[Any, ...], *,
                 cwd: Path | None = None, terminate_wait_s: float = TERMINATE_WAIT_S) -> None:
        self.module, self.label, self.device = module, label, device
        self._close_message = close_message
        self._cwd = cwd
        self._terminate_wait_s = terminate_wait_s
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Connection | None = None
        self._ended = True      # no child yet, or the current one is ended and its channel closed
        self._closed = False
        self._send_lock = threading.Lock()

    # ------------------------------------------------------------------ spawn and handshake
    def spawn(self, extra_fds: Sequence[int] = ()) -> Connection:
        """Start a child (module doc) and return the parent's end of its channel. The caller
        closes its copies of ``extra_fds`` afterwards (the child has its own).

        Raises:
            LifecycleError: after :meth:`close`, or while the previous child is not ended (call
                :meth:`end` first).
            OSError: the interpreter could not be started (nothing is left open here).
        """
        if self._closed:
            raise LifecycleError(self.device, f"start of the {self.label} after close()")
        if not self._ended:
            raise LifecycleError(self.device, f"start of the {self.label} before the previous one ended")
        ours, theirs = socket.socketpair()
        conn = Connection(ours.detach())
        try:
            args = [str(theirs.fileno()), *(str(fd) for fd in extra_fds), str(os.getpid())]
            proc = subprocess.Popen([sys.executable, "-m", self.module, *args],
                                    pass_fds=(theirs.fileno(), *extra_fds), stdin=subprocess.DEVNULL,
                                    cwd=self._cwd)
        except BaseException:
            conn.close()
            raise
        finally:
            theirs.close()
        self._proc, self._conn, self._ended = proc, conn, False
        return conn

    def wait_message(self, receive: Callable[[float], Any], gone: Callable[[], str | None], timeout_s: float,
                     timed_out: str, step_s: float = 0.05) -> Any:
        """The first message ``receive`` accepts, waiting up to ``timeout_s`` (blocking).

        Args:
            receive: reads the channel for up to the given time, s; returns the accepted
                message, or None when none came.
            gone: after each empty ``receive``: why the child is gone (None: it runs).
            timeout_s: how long to wait in all, s. timed_out: the timeout's message.
            step_s: the longest ``receive`` call, s (how soon a gone child is noticed).

        Raises:
            DeviceTimeoutError: nothing accepted within ``timeout_s`` (``timed_out``).
            DisconnectedError: the child is gone (the reason ``gone`` gave).
        """
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeoutError(self.device, timed_out)
            msg = receive(min(remaining, step_s))
            if msg is not None:
                return msg
            why = gone()
            if why is not None:
                raise DisconnectedError(self.device, why)

    def handshake(self, first: Any, *, wait_ready: Callable[[], Any],
                  failed: Callable[[Any], BaseException], published: Callable[[], bool],
                  pause: Callable[[], None], unpublished: str, on_failure: Callable[[], None],
                  timeout_s: float = START_TIMEOUT_S) -> Any:
        """Send the child its first message, wait for its ``ready`` answer, then until its first
        output is there (a servo loop's first state record, a perception process's first pair);
        return the ready payload. On any failure ``on_failure`` runs (the owner ends the child and
        frees what it made for it) before the error propagates. Blocks (module doc).

        Args:
            first: the first message (the spec). wait_ready: waits for the ``ready`` or
                ``failed`` answer (typically :meth:`wait_message`) and raises as it does.
            failed: the error a ``("failed", payload)`` answer raises.
            published: whether the first output is there. pause: waits a little before asking
                again (it may return early). unpublished: the timeout's message.
            timeout_s: how long the first output may take after ``ready``, s.

        Raises:
            what ``wait_ready`` raises; ``failed(payload)``; DeviceTimeoutError
            (``unpublished``) when the child exits or the time runs out before its first output;
            OSError/ValueError when the channel is gone before the first message is sent.
        """
        try:
            self.send(first)
            msg = wait_ready()
            if msg[0] == "failed":
                raise failed(msg[1])
            deadline = time.monotonic() + timeout_s
            while not published():
                if not self.running or time.monotonic() > deadline:
                    raise DeviceTimeoutError(self.device, unpublished)
                pause()
        except BaseException:
            on_failure()
            raise
        return msg[1]

    # ------------------------------------------------------------------ channel and liveness
    def send(self, msg: Any) -> None:
        """Send one message to the current child (sends from several threads are serialised).

        Raises:
            OSError, ValueError: the channel is closed or broken (the child is gone).
        """
        with self._send_lock:
            self.conn.send(msg)

    def send_quietly(self, msg: Any) -> bool:
        """:meth:`send`, never raising; whether it was sent (a gone child is reported elsewhere)."""
        try:
            self.send(msg)
        except (OSError, ValueError):
            return False
        return True

    @property
    def conn(self) -> Connection:
        """The parent's end of the current child's channel (closed once the child is ended)."""
        if self._conn is None:
            raise LifecycleError(self.device, f"the {self.label} was never started")
        return self._conn

    @property
    def started(self) -> bool:
        """A child has been spawned (it may have ended since)."""
        return self._proc is not None

    @property
    def closed(self) -> bool:
        """:meth:`close` was called (a child that ended on its own leaves this False)."""
        return self._closed

    @property
    def running(self) -> bool:
        """The current child has not exited (False before the first spawn). Never blocks."""
        return self._proc is not None and self._proc.poll() is None

    @property
    def exitcode(self) -> int | None:
        """The current child's exit code (negative: the signal that ended it); None while it
        runs or before the first spawn."""
        return self._proc.poll() if self._proc is not None else None

    @property
    def pid(self) -> int | None:
        """The current child's process id (None before the first spawn)."""
        return self._proc.pid if self._proc is not None else None

    def exited(self) -> str:
        """``"<label> exited (code N)"`` (N: :attr:`exitcode`)."""
        return f"{self.label} exited (code {self.exitcode})"

    def wait_exit(self, timeout_s: float) -> int | None:
        """Wait up to ``timeout_s`` for the current child to exit (blocking); its exit code, or
        None when it still runs (or none was spawned)."""
        if self._proc is None:
            return None
        try:
            return self._proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def channel_end_reason(self, wait_s: float = CHANNEL_END_WAIT_S) -> str:
        """Why the channel ended: the child's exit, with its code. The channel closes as the
        child dies, a moment before the OS reports the exit: waits up to ``wait_s`` for it (a code
        read at once was often None, in the operator's fault message and the session log)."""
        code = self.wait_exit(wait_s)
        if code is None:
            return f"{self.label} closed its channel and still runs"
        return f"{self.label} exited (code {code})"

    # ------------------------------------------------------------------ ending and restarting
    def end(self, timeout_s: float = 5.0) -> bool:
        """End the current child (module doc) and close its channel. Returns whether a child was
        ended by this call (False: none was spawned, or it was ended already), so that the owner
        frees what it made for that child exactly once. Never raises."""
        proc = self._proc
        if proc is None or self._ended:
            return False
        self._ended = True
        if proc.poll() is None:
            self.send_quietly(self._close_message)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout_s)
        if proc.poll() is None:
            proc.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(self._terminate_wait_s)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        self.conn.close()
        return True

    def close(self, timeout_s: float = 5.0) -> bool:
        """End the current child for good (:meth:`end`); no spawn after it. Idempotent, never
        raises; returns what :meth:`end` returned (False on every later call)."""
        if self._closed:
            return False
        self._closed = True
        return self.end(timeout_s)

    def check_restart(self, crashed: bool) -> None:
        """Whether a new child may be started in place of the current one: only before
        :meth:`close` and once the current one is gone (exited, or ``crashed``: it reported a
        crash and is on its way out).

        Raises:
            LifecycleError: after :meth:`close` (``restart() after close()``), or while the
                child runs (``restart() while the <label> runs``).
        """
        if self._closed:
            raise LifecycleError(self.device, "restart() after close()")
        if not crashed and self.running:
            raise LifecycleError(self.device, f"restart() while the {self.label} runs")


# ---------------------------------------------------------------------------- child side
def run_child(argv: Sequence[str], module: str, extra_fds: Sequence[str],
              main: Callable[..., None]) -> int:
    """The child's entry (``python -m module FD [EXTRA_FD ...] PARENT_PID``, module doc): calls
    ``main(channel, *extra_fds, parent_pid)`` and returns 0; with other arguments writes the usage
    (one line, naming ``extra_fds``) to stderr and returns 2 (it is started by hil, not by hand)."""
    try:
        if len(argv) != 2 + len(extra_fds):
            raise ValueError("argument count")
        numbers = [int(a) for a in argv]
    except ValueError:
        words = " ".join(["FD", *extra_fds, "PARENT_PID"])
        sys.stderr.write(f"usage: python -m {module} {words} (started by hil, not by hand)\n")
        return 2
    main(Connection(numbers[0]), *numbers[1:])
    return 0
