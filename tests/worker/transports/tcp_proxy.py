"""A TCP proxy that a test can pause, cut or take down, to drop a link on purpose."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterator

import pytest


class CuttableProxy:
    """Forwards 127.0.0.1:`port` to an upstream port, in both directions.

    `pause()` holds the bytes (the connections stay open, as with a pulled cable);
    `cut()` closes every connection; `down()` also closes every new one until `up()`;
    `cut_after()` cuts them once a request arrived, before its answer gets back;
    `throttle()` passes the client's bytes on at a slow pace, as a far side that reads slowly.
    """

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port: int = self._listener.getsockname()[1]
        self._flowing = threading.Event()
        self._flowing.set()
        self._is_down = False
        self.connections = 0  # forwarded so far
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self._cut_after: tuple[bytes, Callable[[], None]] | None = None
        self._client_bytes_per_s: int | None = None
        threading.Thread(target=self._accept, daemon=True).start()

    def pause(self) -> None:
        self._flowing.clear()

    def resume(self) -> None:
        self._flowing.set()

    def throttle(self, bytes_per_s: int | None) -> None:
        """Pass the client's bytes on at `bytes_per_s` from now on (None: at full speed)."""
        self._client_bytes_per_s = bytes_per_s

    def cut(self) -> None:
        with self._lock:
            sockets, self._sockets = self._sockets, []
        for sock in sockets:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()

    def down(self) -> None:
        self._is_down = True
        self.cut()

    def up(self) -> None:
        self._is_down = False

    def cut_after(self, marker: bytes, before_cut: Callable[[], None]) -> None:
        """The next time the client sends `marker`, it is passed on and the answers are
        held; once `before_cut()` has returned, every connection is cut (once)."""
        self._cut_after = (marker, before_cut)

    def close(self) -> None:
        self._listener.close()
        self.resume()
        self.cut()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            if self._is_down:
                client.close()
                continue
            try:
                server = socket.create_connection(("127.0.0.1", self.upstream_port))
            except OSError:
                client.close()
                continue
            with self._lock:
                self.connections += 1
                self._sockets += [client, server]
            for source, sink in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(source, sink, source is client),
                                 daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket, from_client: bool) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                self._flowing.wait()
                trigger = self._cut_after if from_client else None
                if trigger is not None and trigger[0] in data:
                    self._cut_after = None
                    self.pause()  # from before the request arrives: its answer is held
                    sink.sendall(data)
                    trigger[1]()
                    self.cut()
                    self.resume()
                    return
                sink.sendall(data)
                if from_client and (pace := self._client_bytes_per_s):
                    time.sleep(len(data) / pace)
        for sock in (source, sink):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)


@pytest.fixture
def make_proxy() -> Iterator[Callable[[int], CuttableProxy]]:
    """Factory: make_proxy(upstream_port); every proxy is closed after the test."""
    made: list[CuttableProxy] = []

    def make(upstream_port: int) -> CuttableProxy:
        made.append(CuttableProxy(upstream_port))
        return made[-1]

    yield make
    for proxy in made:
        proxy.close()
