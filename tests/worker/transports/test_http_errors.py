"""httpx failures become the transport errors that decide retries, for every HTTP transport.

A loopback server gives the real failures: a refused connection, a peer that hangs up,
endless redirects, a body that cannot be decoded.
"""

from __future__ import annotations

import gzip
import json
import socket
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest

from worker.transports.base import (
    BadPath,
    ConnectFailed,
    Dropped,
    NetworkOptions,
    NotFound,
    Permanent,
    Transient,
    TransportError,
)
from worker.transports.http import http_errors, network_client


class _Handler(BaseHTTPRequestHandler):
    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        if self.path == "/loop":
            self.send_response(302)
            self.send_header("Location", "/loop")
            self.end_headers()
        elif self.path == "/bad-gzip":
            body = b"not gzip at all"
            self.send_response(200)
            self.send_header("Content-Encoding", "gzip")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
        elif self.path == "/echo-key":  # "Invalid API key <key>", in another letter case
            echoed = self.headers.get("X-Api-Key", "").upper()
            body = json.dumps({"error": f"Invalid API key {echoed}"}).encode()
            self.send_response(403)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
        elif self.path.startswith("http://"):  # asked as a proxy: say what was asked for
            body = self.path.encode()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
        elif self.path == "/hang-up":
            self.connection.shutdown(socket.SHUT_RDWR)  # no status line at all
        else:
            body = gzip.compress(b"missing")
            self.send_response(404)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Content-Encoding", "gzip")
            self.end_headers()
            self.wfile.write(body)

    def log_message(self, *_: object) -> None:
        pass


@pytest.fixture(scope="module")
def base_url() -> Iterator[str]:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()


def _get(url: str, key: str = "") -> None:
    with httpx.Client(follow_redirects=True, max_redirects=3, timeout=5) as client, \
            http_errors(url, clean=lambda text: text.replace(key, "***") if key else text):
        client.get(url).raise_for_status()


@pytest.mark.parametrize(("path", "error", "transient"), [
    ("/missing", NotFound, False),
    ("/loop", Permanent, False),  # endless redirects: no retry can help
    ("/bad-gzip", Permanent, False),  # an answer that cannot be decoded
    ("/hang-up", Dropped, True),
])
def test_each_failure_is_transient_or_not_as_a_retry_could_help(
        base_url: str, path: str, error: type[TransportError], transient: bool) -> None:
    with pytest.raises(error) as caught:
        _get(base_url + path)
    assert isinstance(caught.value, Transient) is transient
    assert path in str(caught.value)


def test_a_refused_connection_is_transient() -> None:
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        port = unused.getsockname()[1]
    with pytest.raises(ConnectFailed):
        _get(f"http://127.0.0.1:{port}/x")


def test_a_url_scheme_httpx_cannot_speak_is_permanent_and_the_key_is_blanked() -> None:
    with pytest.raises(BadPath) as caught:
        _get("ftp://secret-key@127.0.0.1/x", key="secret-key")
    assert not isinstance(caught.value, Transient)
    assert "secret-key" not in str(caught.value)
    assert "***" in str(caught.value)


def test_a_key_the_server_echoes_back_in_its_error_is_blanked_in_any_case(base_url) -> None:
    key = "Sekret-Key-0123456789"
    with pytest.raises(TransportError) as caught, \
            httpx.Client(headers={"X-Api-Key": key}, timeout=5) as client, \
            http_errors("/files"):  # no `clean`: the request's own key is blanked anyway
        client.get(base_url + "/echo-key").raise_for_status()
    assert "HTTP 403" in str(caught.value) and "***" in str(caught.value)
    assert key.lower() not in str(caught.value).lower()


def test_a_machine_client_goes_through_the_proxy_the_environment_names(base_url, monkeypatch):
    for name in ("HTTP_PROXY", "http_proxy", "ALL_PROXY", "all_proxy", "NO_PROXY", "no_proxy"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HTTP_PROXY", base_url)  # the loopback server plays the proxy

    with network_client(NetworkOptions(timeout_s=5), base_url="http://machine.invalid/",
                        headers={}) as client:
        answer = client.get("files")

    assert answer.text == "http://machine.invalid/files"
