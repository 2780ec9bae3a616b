"""Headless Chromium driven over the DevTools protocol (tests and the docs screenshot).

:class:`HeadlessChromium` starts Debian's ``chromium`` with the network-quiet flags (no
background networking, no component updates, no sync, no QUIC, a new empty profile) and a
DevTools port on loopback; :meth:`HeadlessChromium.open` loads a page and collects its console
messages, exceptions and every network request the page starts; :meth:`Page.screenshot`
returns a PNG. Every process and socket is
closed by :meth:`HeadlessChromium.close` (use ``with``).
"""

from __future__ import annotations

import base64
import contextlib
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from types import TracebackType
from typing import Any

from websockets.sync.client import ClientConnection, connect

CHROMIUM = "chromium"
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-default-apps", "--disable-extensions", "--no-default-browser-check",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--remote-allow-origins=*",
         # nothing leaves the machine: every host name but loopback resolves to nothing, and every
         # connection not to loopback goes to a dead local proxy (a second line of defence here: a
         # request the page starts to any other host is seen in ``Page.requests`` and fails)
         "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1, EXCLUDE localhost",
         "--proxy-server=127.0.0.1:9", "--proxy-bypass-list=127.0.0.1;localhost")


def chromium_path() -> str | None:
    return shutil.which(CHROMIUM)


class Page:
    """One tab: send DevTools commands, read console messages (``console``: (level, text)),
    uncaught exceptions (``exceptions``) and the URL of every request the page started
    (``requests``: ``Network.requestWillBeSent``, whatever became of the request)."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self._id = 0
        self.console: list[tuple[str, str]] = []
        self.exceptions: list[str] = []
        self.requests: list[str] = []

    def _event(self, msg: dict[str, Any]) -> None:
        method, params = msg.get("method"), msg.get("params", {})
        if method == "Runtime.consoleAPICalled":
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in params.get("args", []))
            self.console.append((params.get("type", ""), text))
        elif method == "Log.entryAdded":
            e = params.get("entry", {})
            text = f"{e.get('source')}: {e.get('text')} {e.get('url', '')}"
            self.console.append((e.get("level", ""), text))
        elif method == "Network.requestWillBeSent":
            self.requests.append(str(params.get("request", {}).get("url", "")))
        elif method == "Runtime.exceptionThrown":
            d = params.get("exceptionDetails", {})
            self.exceptions.append(str(d.get("exception", {}).get("description") or d.get("text")))

    def send(self, method: str, timeout_s: float = 60.0, **params: Any) -> dict[str, Any]:
        """Send one command and return its result (events that arrive meanwhile are recorded)."""
        self._id += 1
        my_id = self._id
        self.ws.send(json.dumps({"id": my_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))
            if msg.get("id") == my_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return dict(msg.get("result", {}))
            self._event(msg)

    def pump(self, seconds: float) -> None:
        """Record events for ``seconds`` (the page works meanwhile)."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                self._event(json.loads(self.ws.recv(timeout=left)))
            except TimeoutError:
                return

    def evaluate(self, expression: str) -> Any:
        r = self.send("Runtime.evaluate", expression=expression, returnByValue=True)
        return r.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float) -> Any:
        """Poll ``expression`` until it is truthy (every 0.25 s of page time) or time is up."""
        deadline = time.monotonic() + timeout_s
        value = self.evaluate(expression)
        while not value and time.monotonic() < deadline:
            self.pump(0.25)
            value = self.evaluate(expression)
        return value

    def screenshot(self) -> bytes:
        return base64.b64decode(self.send("Page.captureScreenshot", format="png")["data"])


class HeadlessChromium:
    """Debian's chromium, headless, DevTools on a loopback port (module doc)."""

    def __init__(self, width: int = 1400, height: int = 800) -> None:
        self.size = (width, height)
        self.proc: subprocess.Popen[bytes] | None = None
        self.profile = Path(tempfile.mkdtemp(prefix="hil-chromium-"))
        self.ws: ClientConnection | None = None
        self._stack = contextlib.ExitStack()

    def start(self, timeout_s: float = 60.0) -> HeadlessChromium:
        exe = chromium_path()
        if exe is None:
            raise FileNotFoundError(CHROMIUM)
        port_file = self.profile / "DevToolsActivePort"
        self.proc = subprocess.Popen(
            [exe, *FLAGS, f"--user-data-dir={self.profile}", "--remote-debugging-port=0",
             f"--window-size={self.size[0]},{self.size[1]}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout_s
        while not (port_file.is_file() and port_file.read_text().count("\n") >= 1):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("chromium did not open its DevTools port")
            time.sleep(0.05)  # polling for the port file chromium writes, not synchronising by sleep
        self.port = int(port_file.read_text().split("\n")[0])
        return self

    def open(self, url: str) -> Page:
        """A new tab on ``url`` with console and exception reporting on."""
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/json/new?about:blank", method="PUT")
        with urllib.request.urlopen(req, timeout=30) as r:
            target = json.loads(r.read())
        self.ws = self._stack.enter_context(
            connect(target["webSocketDebuggerUrl"], max_size=64 << 20, open_timeout=30))
        page = Page(self.ws)
        for domain in ("Runtime.enable", "Log.enable", "Page.enable", "Network.enable"):
            page.send(domain)
        page.send("Emulation.setDeviceMetricsOverride", width=self.size[0], height=self.size[1],
                  deviceScaleFactor=1, mobile=False)
        page.send("Page.navigate", url=url)
        return page

    def close(self) -> None:
        self._stack.close()
        self.ws = None
        proc, self.proc = self.proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> HeadlessChromium:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
