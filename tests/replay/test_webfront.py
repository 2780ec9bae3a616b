"""The loopback front of the web viewer (hil/replay/webfront.py) serving a snapshot taken from a
stand-in for Rerun's web server on loopback: the page is rewritten (hosted links and scripts gone,
the guard first), every response carries the Content-Security-Policy whose script hashes match the
page's inline scripts, assets are served byte for byte with their headers, and requests that are
not a plain GET/HEAD of the snapshot's paths by its loopback name are refused. The front never
talks to Rerun's server after the snapshot. Every server and thread is closed."""

from __future__ import annotations

import contextlib
import http.client
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer

import pytest

from hil.replay.webfront import (
    FETCH_GUARD_JS,
    LoopbackFront,
    WebFrontError,
    content_security_policy,
    guard_index_html,
    inline_script_hashes,
    snapshot_assets,
)

PAGE = """<!doctype html><html><head>
<link rel="preconnect" href="https://fonts.googleapis.com" />
<link href="https://fonts.googleapis.com/css2?family=Inter" rel="stylesheet" />
<link rel="icon" href="favicon.ico" />
<script src="https://fifteen-thirtyeight.rerun.io/script.js"></script>
</head><body><script>delete WebAssembly.instantiateStreaming;</script>
<script src="re_viewer.js"></script><script>load_wasm();</script></body></html>"""
WASM = bytes(range(256)) * 4000  # > one relay chunk


class _Upstream(BaseHTTPRequestHandler):
    server: _QuietServer

    def log_message(self, format: str, *args: object) -> None:
        """Quiet."""

    def do_GET(self) -> None:
        self.server.requests.append(self.path)
        if self.path == "/sw.js":
            self.send_error(500)
            return
        if self.path not in self.server.files:
            self.send_error(404)
            return
        body, kind = self.server.files[self.path]
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("rerun-final-length", str(len(body)))
        self.send_header("X-Upstream-Only", "1")
        self.end_headers()
        self.wfile.write(body)


class _QuietServer(HTTPServer):
    def __init__(self, files: dict[str, tuple[bytes, str]]) -> None:
        super().__init__(("127.0.0.1", 0), _Upstream)
        self.files = files
        self.requests: list[str] = []

    def handle_error(self, request: object, client_address: object) -> None:
        """A client that hangs up early is not an error here."""


FILES = {"/": (PAGE.encode(), "text/html"), "/re_viewer_bg.wasm": (WASM, "application/wasm")}
#: what the front asks the stand-in for (no service worker here: it answers 500 for it)
PATHS = ("/", "/re_viewer.js", "/re_viewer_bg.wasm")


@contextlib.contextmanager
def _upstream(files: dict[str, tuple[bytes, str]]) -> Iterator[_QuietServer]:
    upstream = _QuietServer(files)
    thread = threading.Thread(target=upstream.serve_forever, name="test-upstream")
    thread.start()
    try:
        yield upstream
    finally:
        upstream.shutdown()
        thread.join()
        upstream.server_close()


@pytest.fixture
def front() -> Iterator[LoopbackFront]:
    with _upstream(FILES) as upstream:
        assets = snapshot_assets(int(upstream.server_address[1]), PATHS)
        seen = len(upstream.requests)
        with LoopbackFront(0, assets, grpc_port=45678) as f:
            yield f
        assert len(upstream.requests) == seen   # served from the snapshot: Rerun's server never asked


def _get(port: int, path: str, method: str = "GET",
         host: str | None = None) -> tuple[int, dict[str, str], bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.putrequest(method, path, skip_host=True)
        conn.putheader("Host", host or f"127.0.0.1:{port}")
        conn.endheaders()
        r = conn.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
    finally:
        conn.close()


def test_guard_index_html_removes_hosted_links_and_puts_the_guard_first() -> None:
    html = guard_index_html(PAGE)
    assert "googleapis" not in html
    assert "fifteen-thirtyeight" not in html
    assert 'href="favicon.ico"' in html
    assert '<script src="re_viewer.js">' in html
    assert html.index(FETCH_GUARD_JS) < html.index("delete WebAssembly")
    assert html.count("<script") == PAGE.count("<script") - 1 + 1  # one hosted out, the guard in


def test_a_page_without_scripts_is_refused() -> None:
    with pytest.raises(WebFrontError, match="no <script>"):
        guard_index_html("<html><body>not the viewer</body></html>")


def test_index_is_served_guarded_with_a_policy_naming_its_inline_scripts(front: LoopbackFront) -> None:
    status, headers, body = _get(front.port, "/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A45678%2Fproxy")
    assert status == 200
    page = body.decode()
    assert page == guard_index_html(PAGE)
    hashes = inline_script_hashes(page)
    assert len(hashes) == 3  # the guard and the page's two inline scripts
    assert headers["content-security-policy"] == content_security_policy(45678, hashes)
    assert "connect-src 'self' http://127.0.0.1:45678;" in headers["content-security-policy"]
    assert "default-src 'none'" in headers["content-security-policy"]
    assert headers["referrer-policy"] == "no-referrer"


def test_assets_are_served_byte_for_byte_with_their_headers(front: LoopbackFront) -> None:
    status, headers, body = _get(front.port, "/re_viewer_bg.wasm")
    assert (status, body) == (200, WASM)
    assert headers["content-type"] == "application/wasm"
    assert headers["rerun-final-length"] == str(len(WASM))
    assert "x-upstream-only" not in headers
    assert headers["content-security-policy"] == content_security_policy(45678, [])
    status, head_headers, head_body = _get(front.port, "/re_viewer_bg.wasm", method="HEAD")
    assert (status, head_body, head_headers["rerun-final-length"]) == (200, b"", str(len(WASM)))


@pytest.mark.parametrize(("method", "path", "host", "code"), [
    ("GET", "/missing.js", None, 404),
    ("GET", "/re_viewer.js", None, 404),   # not in the snapshot
    ("GET", "/", "rebound.example.com", 421),
    ("GET", "/", "127.0.0.1:1", 421),
    ("GET", "http://example.com/", None, 400),
    ("GET", "//example.com/", None, 404),  # the stdlib makes it /example.com/: a path here
    ("POST", "/", None, 501),
])
def test_other_requests_are_refused(front: LoopbackFront, method: str, path: str, host: str | None,
                                    code: int) -> None:
    assert _get(front.port, path, method=method, host=host)[0] == code


def test_a_page_that_cannot_be_guarded_is_not_served() -> None:
    with _upstream({"/": (b"<html>no script here</html>", "text/html")}) as upstream, \
            pytest.raises(WebFrontError, match="no <script>"):
        snapshot_assets(int(upstream.server_address[1]), PATHS)


def test_the_snapshot_leaves_out_what_the_server_does_not_have_and_refuses_its_errors() -> None:
    with _upstream(FILES) as upstream:
        port = int(upstream.server_address[1])
        assets = snapshot_assets(port, PATHS)
        assert set(assets) == {"/", "/index.html", "/re_viewer_bg.wasm"}   # no re_viewer.js there
        assert assets["/index.html"] is assets["/"]
        with pytest.raises(WebFrontError, match=r"answered 500 for /sw\.js"):
            snapshot_assets(port, ("/", "/sw.js"))
    with _upstream({}) as upstream, pytest.raises(WebFrontError, match="no page at /"):
        snapshot_assets(int(upstream.server_address[1]), PATHS)


def test_upstream_gone_is_a_typed_error() -> None:
    with pytest.raises(WebFrontError, match="not answering"):
        snapshot_assets(1)   # nothing listens on port 1


def test_close_joins_every_thread(front: LoopbackFront) -> None:
    assert _get(front.port, "/")[0] == 200
    front.close()
    assert not [t for t in threading.enumerate() if t.name == "hil-viewer-front"]


def test_a_busy_port_is_a_typed_error(front: LoopbackFront) -> None:
    with pytest.raises(WebFrontError, match="cannot serve"):
        LoopbackFront(front.port, front.assets, grpc_port=45678).start()
