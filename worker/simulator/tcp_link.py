"""One client connection of the simulated control's TCP server: framed reads, writes safe
from several threads, and a file's bytes in either direction."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable
from typing import BinaryIO

from worker.transports import dnc_wire as wire
from worker.transports.dnc_wire import Command, ErrorCode


class Refused(Exception):
    """A request answered with an ERROR; the connection goes on."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code


class Aborted(Exception):
    """The client abandoned an upload (ABORT_FILE): nothing is stored."""


class Link:
    """One client connection: framed reads, and writes safe from several threads."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.last_heard = time.monotonic()
        self.missed_checks = 0
        self._write = threading.Lock()

    def recv_exactly(self, count: int) -> bytes:
        data = bytearray()
        while len(data) < count:
            part = self.sock.recv(count - len(data))
            if not part:
                raise ConnectionError("the client closed the connection")
            data += part
            self.last_heard = time.monotonic()
            self.missed_checks = 0
        return bytes(data)

    def send(self, command: Command, request_id: int, payload: bytes = b"",
             flags: int = 0) -> None:
        with self._write:
            self.sock.sendall(wire.encode(command, request_id, payload, flags))

    def error(self, request_id: int, code: ErrorCode, message: str) -> None:
        self.send(Command.ERROR, request_id, wire.error_payload(code, message))

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes the thread blocked reading it
        self.sock.close()


def send_file(link: Link, request_id: int, name: str, size: int,
              read: Callable[[int], bytes]) -> None:
    """SEND_FILE(name, size) and FILE_DATA frames of `size` bytes from `read`."""
    link.send(Command.SEND_FILE, request_id, wire.file_payload(name, size))
    sent = 0
    while sent < size:
        data = read(min(wire.MAX_PAYLOAD_BYTES, size - sent))
        if not data:  # shortened under us: pad, so the client's count still ends
            data = b"\0" * (size - sent)
        link.send(Command.FILE_DATA, request_id, data)
        sent += len(data)


def receive_file(link: Link, request_id: int, name: str, size: int, out: BinaryIO) -> None:
    """SEND_FILE(name, size) and its FILE_DATA frames into `out`: the client's side of
    an upload after GET_FILE. Refused (nothing is stored) when another frame comes."""
    header = _upload_frame(link, request_id)
    if header.command is not Command.SEND_FILE or wire.read_file(header.payload) != (
            name, size):
        raise Refused(ErrorCode.OUT_OF_SEQUENCE, "expected SEND_FILE with the name "
                      "and size asked for: nothing stored")
    received = 0
    while received < size:
        data = _upload_frame(link, request_id)
        if data.command is not Command.FILE_DATA or received + len(data.payload) > size:
            raise Refused(ErrorCode.OUT_OF_SEQUENCE, "expected FILE_DATA within the "
                          "size asked for: nothing stored")
        out.write(data.payload)
        received += len(data.payload)


def _upload_frame(link: Link, request_id: int) -> wire.Frame:
    """The next frame of an upload; a heartbeat is answered, before SEND_FILE too (the
    client pings while it waits for GET_FILE), and ABORT_FILE raises Aborted."""
    while True:
        frame = wire.read_frame(link.recv_exactly)
        if frame.command in (Command.KEEP_ALIVE, Command.ABORT_FILE) and frame.payload:
            # Answered as a bad frame anywhere: read whole, so the upload goes on.
            link.error(frame.request_id, ErrorCode.BAD_FRAME, "payload too long for its command")
            continue
        if frame.command is Command.KEEP_ALIVE:
            if frame.request_id:
                link.send(Command.KEEP_ALIVE, frame.request_id)
            continue
        if frame.command is Command.ABORT_FILE:
            link.send(Command.OK, request_id)
            raise Aborted
        return frame
