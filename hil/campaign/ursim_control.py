"""Client of the UR emulator's fault-control channel (``tools/ursim``, TCP port 30200 by default).

The channel is line based: one command line in, one reply line out (``ok [...]`` or ``error ...``).
Commands: ``protective_stop``, ``estop``, ``release``, ``stall [on|off]``, ``drop_connection [S]``,
``pause_stream [S]``, ``stop_program``, ``slow_responses MS``, ``home [Q1..Q6]``, ``status`` (reply
``ok {json}``), ``reset``, ``help``. The fault-injection layer drives the emulator through this class.
"""

from __future__ import annotations

import json
import socket
from typing import Any

from drivers.interfaces.errors import DeviceTimeoutError, DisconnectedError, ProtocolError

DEFAULT_CONTROL_PORT = 30200


class UrsimControl:
    """A connection to the emulator's fault channel. Each call blocks for one reply (``timeout_s``).

    Raises (every method):
        DisconnectedError: cannot connect / connection lost.  DeviceTimeoutError: no reply in time.
        ProtocolError: the emulator answered ``error ...``.
    """

    def __init__(
        self, host: str = "127.0.0.1", port: int = DEFAULT_CONTROL_PORT, timeout_s: float = 5.0
    ) -> None:
        self.host = host
        self.port = port
        self.timeout_s = timeout_s
        self._sock: socket.socket | None = None
        self._buf = b""

    def _connect(self) -> socket.socket:
        if self._sock is None:
            try:
                self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
            except OSError as exc:
                raise DisconnectedError(
                    "ursim", f"fault channel {self.host}:{self.port} unreachable: {exc}") from exc
            self._buf = b""
        return self._sock

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> UrsimControl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def command(self, line: str) -> str:
        """Send one command line; return the text after ``ok`` (may be empty)."""
        sock = self._connect()
        try:
            sock.sendall(line.strip().encode() + b"\n")
            while b"\n" not in self._buf:
                chunk = sock.recv(65536)
                if not chunk:
                    raise DisconnectedError("ursim", "fault channel closed by the emulator")
                self._buf += chunk
        except TimeoutError as exc:
            self.close()
            raise DeviceTimeoutError("ursim", f"no reply to {line.strip()!r} in {self.timeout_s} s") from exc
        except OSError as exc:
            self.close()
            raise DisconnectedError("ursim", f"fault channel: {exc}") from exc
        reply, self._buf = self._buf.split(b"\n", 1)
        text = reply.decode("utf-8", errors="replace")
        if text == "ok":
            return ""
        if text.startswith("ok "):
            return text[3:]
        raise ProtocolError("ursim", f"{line.strip()!r} -> {text}")

    # ------------------------------------------------------------------ convenience
    def protective_stop(self) -> None:
        self.command("protective_stop")

    def estop(self) -> None:
        self.command("estop")

    def release(self) -> None:
        self.command("release")

    def stall(self, on: bool = True) -> None:
        self.command(f"stall {'on' if on else 'off'}")

    def drop_connection(self, outage_s: float = 2.0) -> int:
        """A network outage: abort every client connection and refuse new ones for ``outage_s``
        (0: accept again at once). Returns how many connections were dropped."""
        return int(self.command(f"drop_connection {outage_s}").split("=", 1)[1])

    def pause_stream(self, seconds: float) -> None:
        self.command(f"pause_stream {seconds}")

    def stop_program(self) -> None:
        self.command("stop_program")

    def slow_responses(self, ms: float) -> None:
        self.command(f"slow_responses {ms}")

    def reset(self) -> None:
        """Clear every fault: release e-stop/p-stop, power on, brakes off, no stall/slowness/mute."""
        self.command("reset")

    def home(self, q_rad: list[float] | None = None) -> None:
        """Put the emulated arm at rest at ``q_rad`` (default: its home pose)."""
        self.command("home" if q_rad is None else "home " + " ".join(repr(float(x)) for x in q_rad))

    def status(self) -> dict[str, Any]:
        data = json.loads(self.command("status"))
        if not isinstance(data, dict):
            raise ProtocolError("ursim", "status is not a JSON object")
        return data
