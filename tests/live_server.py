"""A real uvicorn server on a free loopback port, in a thread of the test process.

For tests that need real HTTP: streamed request bodies (the test client reads a body
whole before the app sees it), client disconnects, and the CLI talking to the API.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import uvicorn
from starlette.types import ASGIApp

START_TIMEOUT_S = 10.0
# A loaded machine can stall a request for seconds (a disk flush): httpx's default of 5 s
# would call that a failure of the server.
HTTP_TIMEOUT_S = 30.0
POLL_S = 0.01


@dataclass
class LiveServer:
    """A running server: where it listens, and a way to wait until it has no request left."""

    url: str
    server: uvicorn.Server

    def wait_idle(self, timeout_s: float = 10.0) -> None:
        """Block until no request is being handled (an aborted one may still be running)."""
        _wait_for(lambda: not self.server.server_state.tasks, timeout_s, "requests to finish")


def _wait_for(condition: object, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise TimeoutError(f"gave up waiting for {what} after {timeout_s} s")
        time.sleep(POLL_S)


@contextlib.contextmanager
def serving(app: ASGIApp) -> Iterator[LiveServer]:
    """Serve `app` on 127.0.0.1 at a port the OS picks; stop the server afterwards."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    config = uvicorn.Config(app, host="127.0.0.1", port=port, lifespan="off",
                            log_level="warning", access_log=False)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True,
                              name=f"uvicorn-{port}")
    thread.start()
    try:
        _wait_for(lambda: server.started or not thread.is_alive(), START_TIMEOUT_S,
                  "the server to start")
        if not server.started:
            raise RuntimeError("the test server did not start")
        yield LiveServer(f"http://127.0.0.1:{port}", server)
    finally:
        server.should_exit = True
        thread.join(START_TIMEOUT_S)
        sock.close()
