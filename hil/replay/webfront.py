"""A loopback-only front for Rerun's web viewer: the page may reach nothing but 127.0.0.1.

Rerun 0.41's web viewer, as its own server (``rerun --serve-web``) hands it out, makes the browser
ask the Internet for things: a web-font stylesheet (``fonts.googleapis.com``, a ``<link>`` in its
``index.html``), its usage analytics (``tel.rerun.io``, posted from the wasm with ``fetch``; the web
build has no opt-out, crate ``re_analytics``, ``web/config.rs``), a check for a newer release
(``api.github.com``) and the welcome screen's examples manifest (``app.rerun.io``). A clinical
tool must not. :class:`LoopbackFront` is a small HTTP server on 127.0.0.1 that the user's browser
talks to instead. It serves the viewer's assets from a snapshot (:func:`snapshot_assets`, taken
once from a short-lived Rerun web server on a private loopback port, which is then ended: no
unguarded copy of the page stays reachable while the recording is served) and:

* rewrites ``index.html`` (:func:`guard_index_html`): every ``<link>`` and ``<script src>`` naming
  a host is removed, and a first script (:data:`FETCH_GUARD_JS`) wraps ``fetch``,
  ``XMLHttpRequest``, ``navigator.sendBeacon`` and ``WebSocket`` so that a request to any host but
  loopback is refused inside the page, before the browser starts it (a ``fetch`` is answered
  with a local 403 response, which the viewer handles as a server's refusal) (the refused addresses are
  kept in ``window.__hilBlockedRequests``, read by the browser test);
* sends every response with a Content-Security-Policy (:func:`content_security_policy`) that lets
  the page connect only to itself and to the recording's gRPC port on 127.0.0.1, load scripts
  only from itself (plus the hashes of its own inline scripts) and fonts only from itself: should
  the guard miss a way out, the browser itself refuses it;
* answers only ``GET``/``HEAD`` of the snapshot's paths whose ``Host`` is ``127.0.0.1:<port>`` or
  ``localhost:<port>`` (421 otherwise: a page from elsewhere cannot reach it through DNS
  rebinding; 404 for a path the snapshot does not hold).

Threads: one serving thread (``hil-viewer-front``) plus one per request; :meth:`LoopbackFront.close`
stops and joins them all (a client that stops reading times out after :data:`SOCKET_TIMEOUT_S`).
"""

from __future__ import annotations

import base64
import hashlib
import re
import sys
import threading
import urllib.error
import urllib.request
from collections.abc import Mapping
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from types import TracebackType

from hil.errors import HilError
from hil.log import get_logger

_log = get_logger(__name__)

#: Log event: a request to the front failed unexpectedly (its error type; the request is dropped).
EV_FRONT_REQUEST_FAILED = "viewer_front_request_failed"

LOOPBACK = "127.0.0.1"
#: Seconds a request's socket (to the browser, and to Rerun's server while snapshotting) may stay
#: silent.
SOCKET_TIMEOUT_S = 10.0
#: Bytes written per call to the browser (the viewer's wasm is ~43 MB).
CHUNK_BYTES = 1 << 18
#: Response headers kept from Rerun's server (the page reads ``rerun-final-length``).
RELAYED_HEADERS = ("content-type", "content-encoding", "rerun-final-length")
#: The pages that are ``index.html`` (served rewritten).
INDEX_PATHS = ("/", "/index.html")
#: What the viewer's page loads from its server (Rerun 0.41: the page, its script and wasm, the
#: icons and the service worker); a path Rerun's server does not have is left out of the snapshot.
ASSET_PATHS = ("/", "/re_viewer.js", "/re_viewer_bg.wasm", "/favicon.ico", "/favicon.svg",
               "/apple-touch-icon.png", "/sw.js", "/manifest.json")

#: The first script of the page: every request to a host but loopback is refused in the page.
FETCH_GUARD_JS = """
(function () {
  "use strict";
  var LOOPBACK = ["127.0.0.1", "localhost", "[::1]"];
  var blocked = [];
  Object.defineProperty(window, "__hilBlockedRequests", { value: blocked });
  function allowed(url) {
    var u;
    try { u = new URL(String(url), window.location.href); } catch (e) { return false; }
    if (u.protocol === "blob:" || u.protocol === "data:") { return true; }
    return ["http:", "https:", "ws:", "wss:"].indexOf(u.protocol) >= 0 &&
      LOOPBACK.indexOf(u.hostname) >= 0;
  }
  var REFUSED = "refused by hil replay: not a loopback address";
  function refuse(url) {
    blocked.push(String(url).split("?")[0]);
    return new TypeError(REFUSED);
  }
  var realFetch = window.fetch.bind(window);
  window.fetch = function (input, init) {
    var url = (input instanceof Request) ? input.url : input;
    if (!allowed(url)) {  // answered here with a 403, as a server refusing it would
      refuse(url);
      return Promise.resolve(new Response("", { status: 403, statusText: REFUSED }));
    }
    return realFetch(input, init);
  };
  var realOpen = XMLHttpRequest.prototype.open;
  XMLHttpRequest.prototype.open = function (method, url) {
    if (!allowed(url)) { throw refuse(url); }
    return realOpen.apply(this, arguments);
  };
  if (navigator.sendBeacon) {
    var realBeacon = navigator.sendBeacon.bind(navigator);
    navigator.sendBeacon = function (url, data) {
      if (!allowed(url)) { refuse(url); return false; }
      return realBeacon(url, data);
    };
  }
  var RealWebSocket = window.WebSocket;
  window.WebSocket = function (url, protocols) {
    if (!allowed(url)) { throw refuse(url); }
    return new RealWebSocket(url, protocols);
  };
  window.WebSocket.prototype = RealWebSocket.prototype;
  ["CONNECTING", "OPEN", "CLOSING", "CLOSED"].forEach(function (k) {
    window.WebSocket[k] = RealWebSocket[k];
  });
})();
"""

_HOSTED_LINK = re.compile(r"<link\b[^>]*\bhref\s*=\s*[\"']?(?:https?:)?//[^>]*>", re.IGNORECASE)
_HOSTED_SCRIPT = re.compile(r"<script\b[^>]*\bsrc\s*=\s*[\"']?(?:https?:)?//[^>]*>\s*</script>",
                            re.IGNORECASE)
_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.IGNORECASE | re.DOTALL)
_FIRST_SCRIPT = re.compile(r"<script\b", re.IGNORECASE)


class WebFrontError(HilError):
    """The viewer's page cannot be served safely (its ``index.html`` is not as expected, or the
    front's port is busy)."""


def guard_index_html(html: str) -> str:
    """``index.html`` of Rerun's web viewer with every hosted ``<link>``/``<script src>`` removed
    and :data:`FETCH_GUARD_JS` inserted before its first script.

    Raises:
        WebFrontError: the page has no ``<script>`` (not the viewer's page: nothing is served).
    """
    html = _HOSTED_SCRIPT.sub("", _HOSTED_LINK.sub("", html))
    first = _FIRST_SCRIPT.search(html)
    if first is None:
        raise WebFrontError("the web viewer's index.html has no <script>: not Rerun's viewer page")
    return f"{html[:first.start()]}<script>{FETCH_GUARD_JS}</script>\n{html[first.start():]}"


def inline_script_hashes(html: str) -> list[str]:
    """The CSP source expressions (``'sha256-…'``) of the page's inline scripts, in order."""
    return ["'sha256-" + base64.b64encode(hashlib.sha256(body.encode("utf-8")).digest()).decode()
            + "'" for body in _INLINE_SCRIPT.findall(html)]


def content_security_policy(grpc_port: int, script_hashes: list[str]) -> str:
    """The policy sent with every response: the page connects to itself and to
    ``http://127.0.0.1:<grpc_port>`` (the recording) only; scripts from itself and the given
    inline hashes (plus compiling WebAssembly); nothing else from anywhere."""
    scripts = " ".join(["'self'", "'wasm-unsafe-eval'", *script_hashes])
    return "; ".join([
        "default-src 'none'", f"script-src {scripts}", "style-src 'self' 'unsafe-inline'",
        "img-src 'self' data: blob:", "font-src 'self'", "media-src 'self' blob:",
        f"connect-src 'self' http://{LOOPBACK}:{grpc_port}", "worker-src 'self' blob:",
        "manifest-src 'self'", "frame-src 'none'", "object-src 'none'", "base-uri 'none'",
        "form-action 'none'", "frame-ancestors 'none'"])


@dataclass(frozen=True)
class Asset:
    """One file of the viewer as the front serves it: its headers (:data:`RELAYED_HEADERS`) and
    body; ``script_hashes``: the CSP hashes of its inline scripts (the guarded page only)."""

    headers: Mapping[str, str]
    body: bytes
    script_hashes: tuple[str, ...] = ()


def snapshot_assets(upstream_port: int, paths: tuple[str, ...] = ASSET_PATHS) -> dict[str, Asset]:
    """The viewer's files from Rerun's web server on ``127.0.0.1:upstream_port``, the page
    guarded (:func:`guard_index_html`; under every name of :data:`INDEX_PATHS`). Blocks for the
    transfer (~43 MB over loopback).

    Raises:
        WebFrontError: the server does not answer, or has no page, or a page that cannot be
            guarded (nothing is served then).
    """
    out: dict[str, Asset] = {}
    for path in paths:
        try:
            with urllib.request.urlopen(f"http://{LOOPBACK}:{upstream_port}{path}",
                                        timeout=SOCKET_TIMEOUT_S) as r:
                headers = {k: v for k, v in r.headers.items() if k.lower() in RELAYED_HEADERS}
                out[path] = Asset(headers, r.read())
        except urllib.error.HTTPError as exc:
            exc.close()
            if exc.code != 404:
                raise WebFrontError(f"the Rerun web viewer answered {exc.code} for {path}") from None
        except OSError as exc:
            raise WebFrontError(f"the Rerun web viewer is not answering ({exc})") from None
    index = out.get("/")
    if index is None:
        raise WebFrontError("the Rerun web viewer has no page at /")
    try:
        page = guard_index_html(index.body.decode("utf-8"))
    except UnicodeDecodeError:
        raise WebFrontError("the web viewer's index.html is not UTF-8: not Rerun's viewer page") from None
    guarded = Asset({"Content-Type": "text/html; charset=utf-8"}, page.encode("utf-8"),
                    tuple(inline_script_hashes(page)))
    for name in INDEX_PATHS:
        out[name] = guarded
    return out


class _FrontServer(ThreadingHTTPServer):
    daemon_threads = False  # server_close() joins the request threads
    block_on_close = True

    def __init__(self, port: int, assets: Mapping[str, Asset], grpc_port: int) -> None:
        super().__init__((LOOPBACK, port), _FrontHandler)
        self.assets = assets
        self.grpc_port = grpc_port
        bound = self.server_address[1]
        self.allowed_hosts = {f"{LOOPBACK}:{bound}", f"localhost:{bound}"}

    def handle_error(self, request: object, client_address: object) -> None:
        """Log the failure as one event (not the stdlib's traceback on the CLI's stderr)."""
        _log.warning(EV_FRONT_REQUEST_FAILED, error=type(sys.exc_info()[1]).__name__)


class _FrontHandler(BaseHTTPRequestHandler):
    server: _FrontServer
    timeout = SOCKET_TIMEOUT_S
    server_version = "hil-replay"

    def log_message(self, format: str, *args: object) -> None:
        """Silent: the CLI's stdout/stderr carry its own lines only."""

    def do_GET(self) -> None:
        self._serve(with_body=True)

    def do_HEAD(self) -> None:
        self._serve(with_body=False)

    def _serve(self, with_body: bool) -> None:
        if self.headers.get("Host", "") not in self.server.allowed_hosts:
            self.send_error(421, "only 127.0.0.1 serves this viewer")
            return
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        if not path.startswith("/") or path.startswith("//"):  # only this server's own paths
            self.send_error(400, "not a path of this server")
            return
        asset = self.server.assets.get(path)
        if asset is None:
            self.send_error(404)
            return
        csp = content_security_policy(self.server.grpc_port, list(asset.script_hashes))
        try:
            self._start(200, {**asset.headers, "Content-Length": str(len(asset.body))}, csp)
            view = memoryview(asset.body)
            for k in range(0, len(view) if with_body else 0, CHUNK_BYTES):
                self.wfile.write(view[k:k + CHUNK_BYTES])
        except OSError:  # the browser went away mid-response
            self.close_connection = True

    def _start(self, code: int, headers: Mapping[str, str], csp: str) -> None:
        self.send_response(code)
        for name, value in headers.items():
            self.send_header(name, value)
        self.send_header("Content-Security-Policy", csp)
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()


class LoopbackFront:
    """The front (module doc) on ``127.0.0.1:port`` serving the viewer's ``assets``
    (:func:`snapshot_assets`), the recording on ``127.0.0.1:grpc_port``. :meth:`start` binds
    and serves on a thread; :meth:`close` (idempotent) stops it and joins every thread.

    Raises (start):
        WebFrontError: the port cannot be bound (in use).
    """

    def __init__(self, port: int, assets: Mapping[str, Asset], grpc_port: int) -> None:
        self.port = port
        self.assets = assets
        self.grpc_port = grpc_port
        self._server: _FrontServer | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> LoopbackFront:
        try:
            self._server = _FrontServer(self.port, self.assets, self.grpc_port)
        except OSError as exc:
            raise WebFrontError(f"{LOOPBACK}:{self.port}: cannot serve the viewer there: "
                                f"{exc.strerror or exc}") from None
        self.port = int(self._server.server_address[1])
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="hil-viewer-front", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        server, self._server = self._server, None
        thread, self._thread = self._thread, None
        if server is None:
            return
        if thread is not None:
            server.shutdown()  # returns once serve_forever has stopped
            thread.join()
        server.server_close()  # joins the request threads

    def __enter__(self) -> LoopbackFront:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
