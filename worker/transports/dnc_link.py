"""One connection to a control over the seed protocol: requests, replies, ping checks.

The link is opened lazily and kept; replies are matched to requests by id. While waiting
for bytes, each `heartbeat_interval_s` of silence is one failed check: a KEEP_ALIVE is sent
as a ping, and after `ping_checks` failed checks in a row the link is down (`Dropped`); a
ping's answer is checked as any reply.
The control's ERROR replies map onto the error tree here, once; a reply whose payload does
not decode is answered BAD_FRAME and raised as BadFrame, the link kept.
"""

from __future__ import annotations

import contextlib
import itertools
import socket
import threading
import time
from collections.abc import Callable
from typing import TypeVar

from pydantic import Field

from worker.transports import dnc_wire as wire
from worker.transports.base import (
    BadPath,
    Busy,
    ConnectFailed,
    Dropped,
    Exists,
    NetworkOptions,
    NotFound,
    Permanent,
    TimedOut,
    Transient,
    TransportError,
    Unsupported,
)
from worker.transports.dnc_wire import Command, ErrorCode, Frame, WireError

T = TypeVar("T")


class DncOptions(NetworkOptions):
    """How to reach a control over the seed protocol (docs/dnc-protocol.md)."""

    host: str
    port: int = Field(default=4700, ge=1, le=65535)
    heartbeat_interval_s: float = Field(default=2.0, gt=0)
    """Silence on the link after which a KEEP_ALIVE is sent (one ping check)."""
    ping_checks: int = Field(default=3, ge=1)
    """Failed ping checks in a row before the link is declared down."""
    grace_s: float = Field(default=30.0, ge=0)
    """How long a DNC run may reconnect and resume before it fails (LinkLost)."""
    poll_interval_s: float = Field(default=0.05, gt=0)
    """Wait between DNC polls while the control's window is full, and between asks for a
    program the operator punched or for the control's READ (machine-initiated requests).
    In a DNC run it is the shortest wait between rounds (a round that sent lines to a
    control about to run dry loops at once)."""
    max_poll_interval_s: float = Field(default=0.25, gt=0)
    """Longest wait between rounds of a DNC run, and so between two line syncs: a round
    waits a quarter of the time the lines the control holds ahead of its running line last
    at its recent block rate, within poll_interval_s and this."""
    max_receive_bytes: int = Field(default=1024 * 1024, gt=0)
    """Longest program `receive_program` takes (a request the operator punched): a longer
    one is read to its end, dropped and refused, never held whole in memory."""


_ERRORS: dict[int, type[TransportError]] = {
    ErrorCode.NOT_FOUND: NotFound,
    ErrorCode.EXISTS: Exists,
    ErrorCode.BAD_NAME: BadPath,
    ErrorCode.BUSY: Busy,
    ErrorCode.UNKNOWN_COMMAND: Unsupported,
    ErrorCode.BAD_VERSION: Unsupported,
    ErrorCode.INTERNAL: Transient,
}


class ControlError(Permanent):
    """An ERROR reply the tree has no closer class for; `code` is the wire's."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


class BadFrame(Permanent):
    """A frame of the control's whose payload does not decode as its command's: answered
    BAD_FRAME, as the protocol says; it was read whole, so the link goes on."""


def refusal(code: int, message: str) -> TransportError:
    """The error-tree exception for an ERROR reply."""
    cls = _ERRORS.get(code)
    return cls(message) if cls is not None else ControlError(code, message)


class DncLink:
    """A kept connection; the caller holds `lock` around each exchange."""

    def __init__(self, options: DncOptions) -> None:
        self.options = options
        self.lock = threading.RLock()
        self._sock: socket.socket | None = None
        self._buffer = bytearray()
        self._ids = itertools.count(1)
        self._probes: set[int] = set()  # ids of the pings not answered yet
        self.last_used = time.monotonic()

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def connect(self) -> None:
        """Open the connection unless it is open."""
        if self._sock is not None:
            return
        where = f"{self.options.host}:{self.options.port}"
        try:
            sock = socket.create_connection((self.options.host, self.options.port),
                                            timeout=self.options.timeout_s)
        except TimeoutError as exc:
            raise TimedOut(f"connect to {where}: no answer in {self.options.timeout_s:g} s"
                           ) from exc
        except OSError as exc:
            raise ConnectFailed(f"connect to {where}: {exc.strerror or exc}") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock, self._buffer = sock, bytearray()
        self._probes.clear()

    def close(self) -> None:
        """Drop the connection (the next exchange opens a new one)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def send(self, command: Command, payload: bytes = b"", *, request_id: int | None = None
             ) -> int:
        """Send one frame; return its request id."""
        self.connect()
        assert self._sock is not None
        rid = next(self._ids) if request_id is None else request_id
        try:
            self._sock.settimeout(self.options.heartbeat_interval_s)  # a read may have cut it
            self._sock.sendall(wire.encode(command, rid, payload))
        except OSError as exc:
            self.close()
            raise Dropped(f"sending {command.name}: {exc}") from exc
        self.last_used = time.monotonic()
        return rid

    def request(self, command: Command, payload: bytes = b"") -> Frame:
        """Send a request and return its first reply (an ERROR is raised, mapped)."""
        return self.reply(self.send(command, payload))

    def reply(self, request_id: int) -> Frame:
        """The next frame answering `request_id`; pings are answered, stale frames skipped."""
        deadline = time.monotonic() + self.options.timeout_s
        while True:
            frame = self._frame(deadline)
            if frame.command is Command.KEEP_ALIVE and frame.request_id == 0:
                self._answer_ping(frame)
            elif frame.request_id in self._probes:
                self._probes.discard(frame.request_id)
                with contextlib.suppress(BadFrame):  # answered; it answers no request
                    self._check_pong(frame)
            elif frame.request_id not in (request_id, 0):
                continue  # the answer to a request given up on
            elif frame.command is Command.ERROR:
                code, message = self.decode(frame, wire.read_error)
                raise refusal(code, f"the control refused: {message}")
            else:
                return frame

    def decode(self, frame: Frame, read: Callable[[bytes], T]) -> T:
        """The fields `read` takes from the frame's payload; BadFrame when they are not
        there, once the control has been told (ERROR BAD_FRAME, the frame's request id)."""
        try:
            return read(frame.payload)
        except WireError as exc:
            self.send(Command.ERROR, wire.error_payload(ErrorCode.BAD_FRAME, str(exc)),
                      request_id=frame.request_id)
            raise BadFrame(f"the control sent a bad {frame.command.name} ({exc})") from exc

    def ping(self) -> None:
        """Send a KEEP_ALIVE and check its answer (`_check_pong`)."""
        self._check_pong(self.request(Command.KEEP_ALIVE))

    def _check_pong(self, frame: Frame) -> None:
        """The answer to a KEEP_ALIVE of ours is a KEEP_ALIVE with an empty payload: one
        with bytes is answered BAD_FRAME (BadFrame), one of another kind is out of step
        (Dropped, the link closed), as any reply of the wrong kind."""
        if frame.command is not Command.KEEP_ALIVE:
            self.close()
            raise Dropped(f"the control answered a KEEP_ALIVE with {frame.command.name}")
        self.decode(frame, lambda payload: wire.read_uint(payload, 0))

    def _answer_ping(self, frame: Frame) -> None:
        """Answer the control's ping check; one with a payload is answered BAD_FRAME, and
        fails no request (it answers none)."""
        with contextlib.suppress(BadFrame):
            self.decode(frame, lambda payload: wire.read_uint(payload, 0))
            self.send(Command.KEEP_ALIVE, request_id=0)

    def _frame(self, deadline: float) -> Frame:
        while True:
            try:
                return wire.read_frame(lambda count: self._recv_exactly(count, deadline))
            except WireError as exc:
                if exc.code is ErrorCode.UNKNOWN_COMMAND and exc.resync:
                    # A command of a later revision of version 1: answered as the protocol
                    # says, and the link goes on (dropping it and resuming met the same
                    # command again, round after round).
                    self.send(Command.ERROR, wire.error_payload(
                        ErrorCode.UNKNOWN_COMMAND, str(exc)), request_id=exc.request_id)
                    continue
                self.close()  # its replies cannot be trusted any more
                raise Dropped(f"the control sent a bad frame: {exc}") from exc

    def _recv_exactly(self, count: int, deadline: float) -> bytes:
        misses = 0
        while len(self._buffer) < count:
            if self._sock is None:
                raise Dropped("the connection was closed")
            left_s = deadline - time.monotonic()
            if left_s <= 0:
                self.close()
                raise TimedOut(f"no reply within {self.options.timeout_s:g} s (timeout_s)")
            try:
                # timeout_s bounds the wait even when a heartbeat interval is longer
                self._sock.settimeout(min(left_s, self.options.heartbeat_interval_s))
                part = self._sock.recv(max(65536, count - len(self._buffer)))
            except TimeoutError:
                if left_s < self.options.heartbeat_interval_s:
                    continue  # no check failed: the deadline passed, raised above
                misses += 1
                if misses >= self.options.ping_checks:
                    self.close()
                    raise Dropped(f"link down: {misses} ping checks of "
                                  f"{self.options.heartbeat_interval_s:g} s failed") from None
                self._probes.add(self.send(Command.KEEP_ALIVE))
                continue
            except OSError as exc:
                self.close()
                raise Dropped(f"receiving: {exc}") from exc
            if not part:
                self.close()
                raise Dropped("the control closed the connection")
            self._buffer += part
            misses = 0
        data = bytes(self._buffer[:count])
        del self._buffer[:count]
        return data

    def heartbeat(self) -> None:
        """Send a KEEP_ALIVE and wait for it, when the link is idle and open."""
        if not self.lock.acquire(blocking=False):
            return  # an exchange is going on: it checks the link itself
        try:
            idle_s = time.monotonic() - self.last_used
            if self._sock is None or idle_s < self.options.heartbeat_interval_s:
                return
            try:
                self.ping()
            except BadFrame:
                pass  # answered BAD_FRAME: read whole, the link is in step
            except TransportError:
                self.close()  # the next operation connects again
        finally:
            self.lock.release()
