"""The simulated control's RS-232 side: a pseudo-terminal, a device, or a raw TCP port.

What a control's serial interface does, on one `Control`:

- In EDIT or MEM mode it reads in programs punched to it: from a start `%` (ISO) or EOR
  (0x0B, EIA: the code is recognised per program, as a Fanuc does) to the next one, and
  stores them under the name of their O-number (or first word, per the store's naming),
  never over a stored one.
- When its operator presses READ (`Control.press_read`) it sends DC1 and reads in the
  next program, in any mode while no DNC run goes on, replacing its namesake; then it
  sends DC3 (a Fanuc with DC codes on).
- In DNC mode it executes a program fed from the line: bytes go into a receive buffer of
  `buffer_bytes`; whole lines move from it into the control as its memory
  (`lookahead_lines`) frees up. It sends DC3 when the buffer fills past `high_mark_bytes`
  and DC1 when it drains below `low_mark_bytes`; the end character ends the data. What
  comes beyond the buffer is lost and counted in `overflowed_bytes`, as in a UART overrun.
  A control's UART takes each byte as it comes; this one looks at the line from a thread,
  which a loaded host may keep from running for a while. What the line carried meanwhile
  (at most `baud`'s rate for that time) a real control would have met with an earlier
  DC3, so the buffer stretches for it rather than blame the sender: a sender that ignores
  DC3, or outruns the line, still overflows it.
- It punches a stored program when asked (`request_punch(name)`), or a program typed at
  the control (`punch_text(data)`); the operator panel (worker.simulator.panel) presses
  those keys too.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import select
import socket
import stat
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

from worker.simulator.control import Control, DncRefused, IoChannel, Mode, NotReadyToRead
from worker.transports import eia
from worker.transports.base import TransportError
from worker.transports.serial_tape import NOISE, XOFF, XON, program_name

log = logging.getLogger(__name__)

ISO_START, EIA_START = ord("%"), eia.EIA_EOR
_LEADER = b"\0" * 20  # blank tape around a punch
_LOOK_S = 0.005  # longest wait for the line before the control's other work
_MOST_A_LOOK = 1 << 20  # bytes one look takes at most (a sender writing without end)


class PtyEnd:
    """The control's end of a pseudo-terminal pair, or of a device given by path."""

    def __init__(self, path: Path) -> None:
        """Args:
        path: a character device to open, or where to link the new pty's other end.
        """
        self._slave: int | None = None
        if path.exists() and stat.S_ISCHR(path.stat().st_mode):
            self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
            self.device = str(path)
        else:
            self.fd, self._slave = os.openpty()
            # Raw before anyone opens it: no echo, no line editing of the program.
            tty.setraw(self._slave)
            self.device = os.ttyname(self._slave)
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            path.symlink_to(self.device)
            self.link = path
        tty.setraw(self.fd)

    def read(self, timeout_s: float) -> bytes:
        """All that came, waiting up to `timeout_s` for the first of it.

        A pty hands over at most its line discipline's 4 KB a read: what the line carried
        while the control did not look, beyond that, is waiting behind it at once and is
        taken in the same look (the control's thread may have been kept from running).
        """
        ready, _, _ = select.select([self.fd], [], [], timeout_s)
        if not ready:
            return b""
        chunks = [os.read(self.fd, 65536)]
        taken = len(chunks[0])
        while taken < _MOST_A_LOOK and select.select([self.fd], [], [], 0)[0]:
            try:
                chunk = os.read(self.fd, 65536)
            except OSError:  # the other end closed: the next look says so
                break
            if not chunk:
                break
            chunks.append(chunk)
            taken += len(chunk)
        return b"".join(chunks)

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.fd, view):]

    def close(self) -> None:
        os.close(self.fd)
        if self._slave is not None:  # ours kept the pty up while no one else had it open
            os.close(self._slave)
            with contextlib.suppress(OSError):
                self.link.unlink()


class TcpRawEnd:
    """A raw TCP port, as a serial device server offers: the newest client has the line."""

    def __init__(self, host: str, port: int) -> None:
        self._listener = socket.create_server((host, port))
        self.port: int = self._listener.getsockname()[1]
        self._client: socket.socket | None = None
        self.device = f"tcp {host} {self.port}"

    @property
    def connected(self) -> bool:
        """True while a client has the line (what is written before reaches no one)."""
        return self._client is not None

    def read(self, timeout_s: float) -> bytes:
        watched = [self._listener] + ([self._client] if self._client else [])
        ready, _, _ = select.select(watched, [], [], timeout_s)
        if self._listener in ready:
            if self._client is not None:
                self._client.close()
            self._client, _ = self._listener.accept()
            self._client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return b""
        if self._client is None or self._client not in ready:
            return b""
        try:
            data = self._client.recv(65536)
        except OSError:
            data = b""
        if not data:  # the client went away: the line is free
            self._client.close()
            self._client = None
        return data

    def write(self, data: bytes) -> None:
        if self._client is not None:
            try:
                self._client.sendall(data)
            except OSError:
                self._client.close()
                self._client = None

    def close(self) -> None:
        self._listener.close()
        if self._client is not None:
            self._client.close()


class SerialMachine:
    """Serves one `Control` over one line end; `start()` returns at once."""

    def __init__(self, control: Control, end: PtyEnd | TcpRawEnd, *,
                 buffer_bytes: int = 1024, high_mark_bytes: int | None = None,
                 low_mark_bytes: int | None = None, lookahead_lines: int = 8,
                 baud: int = 115_200) -> None:
        """Args:
        baud: the fastest the line is set to run; it bounds what the line may have
            carried while this thread did not look (8N1: ten bits a character).
        """
        self.control = control
        self.end = end
        self.buffer_bytes = buffer_bytes
        self.chars_per_s = baud / 10
        self.high_mark_bytes = high_mark_bytes or buffer_bytes // 2
        self.low_mark_bytes = low_mark_bytes if low_mark_bytes is not None else buffer_bytes // 8
        if not 0 <= self.low_mark_bytes < self.high_mark_bytes <= buffer_bytes:
            raise ValueError("marks must satisfy 0 <= low < high <= buffer_bytes")
        self.lookahead_lines = lookahead_lines
        self._rx = bytearray()  # DNC receive buffer
        self._room = buffer_bytes  # what it holds before an overrun: stretched when late
        self._looked_at = time.monotonic()  # the line is open from here on
        self._tape = bytearray()  # a program being read in (EDIT, MEM)
        self._tape_code: int | None = None  # its start code: ISO or EIA
        self._dnc_code: int | None = None  # start code of the DNC tape being run
        self._dnc_name: str | None = None
        self.xoff_sent = False
        self.peak_buffer_bytes = 0
        self.overflowed_bytes = 0
        self.xoff_count = 0
        self.received: list[str] = []  # programs read in, by name
        self.last_error: str | None = None
        self._keys: queue.Queue[Callable[[], None]] = queue.Queue()  # run on the line's thread
        self._read_presses = control.read_presses  # READ presses answered with a DC1
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="serial", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._closed.set()
        self._thread.join(5)
        self.end.close()

    def request_punch(self, name: str) -> None:
        """The operator presses PUNCH with program `name` selected."""
        self._keys.put(lambda: self._punch(name))

    def punch_text(self, data: bytes) -> None:
        """The operator punches a program typed at the control (`data`: its ISO text)."""
        self._keys.put(lambda: self._punch_text(data))

    def reset(self) -> None:
        """The operator's RESET: the run stops, what the buffer holds is dropped."""
        self._keys.put(self._reset)

    def status(self) -> dict[str, Any]:
        """What the panel's status.json shows of this side."""
        return {"buffer_bytes": len(self._rx), "peak_buffer_bytes": self.peak_buffer_bytes,
                "overflowed_bytes": self.overflowed_bytes, "xoff_count": self.xoff_count,
                "received": self.received, "last_error": self.last_error}

    # -- the line's thread -------------------------------------------------------

    def _serve(self) -> None:
        while not self._closed.is_set():
            try:
                data = self.end.read(_LOOK_S)
                now = time.monotonic()
                if data:
                    self._take(data, unseen_s=now - self._looked_at)
                self._looked_at = now
                self._feed()
                while not self._keys.empty():
                    self._keys.get()()
                if self._read_presses != self.control.read_presses:
                    self._read_presses = self.control.read_presses
                    self.end.write(XON)  # READ: the control starts the PC's reader
            except Exception as exc:  # a simulator never stops on what the line brings
                log.exception("serial line")
                self.last_error = str(exc)

    def _take(self, data: bytes, unseen_s: float) -> None:
        """`data` came in during the `unseen_s` since the line was last looked at."""
        c = self.control
        if c.mode is Mode.DNC and not (c.ready_to_read and not c.active):
            if not self.xoff_sent:
                # Had this thread looked in time, DC3 would have gone out at the high mark
                # and the sender had the buffer's headroom to stop in.
                carried = min(len(data), int(unseen_s * self.chars_per_s))
                headroom = self.buffer_bytes - self.high_mark_bytes
                self._room = max(self._room, len(self._rx) + carried + headroom)
            self._rx += data
            if len(self._rx) > self._room:  # a UART overrun: the rest is lost
                self.overflowed_bytes += len(self._rx) - self._room
                del self._rx[self._room:]
            self.peak_buffer_bytes = max(self.peak_buffer_bytes, len(self._rx))
            if not self.xoff_sent and len(self._rx) >= self.high_mark_bytes:
                self.end.write(XOFF)
                self.xoff_sent = True
                self.xoff_count += 1
        else:
            self._read_in(data)

    # -- reading programs in -----------------------------------------------------

    def _read_in(self, data: bytes) -> None:
        for byte in data:
            if self._tape_code is None:
                if byte in (ISO_START, EIA_START):
                    self._tape_code = byte
                    self._tape = bytearray([byte])
            elif byte == self._tape_code:
                self._tape.append(byte)
                self._store(bytes(self._tape), self._tape_code)
                self._tape_code = None
            else:
                self._tape.append(byte)

    def _store(self, tape: bytes, code: int) -> None:
        text = eia.decode(tape) if code == EIA_START else tape.translate(None, NOISE)
        name = program_name(text)
        asked = self.control.ready_to_read  # READ pressed: this one replaces its namesake
        try:
            if name is None:
                raise ValueError("the program has no name on its first line")
            with (self.control.read_in(name) if asked else
                  self.control.store.receive(name)) as out:
                out.write(text + b"\n")
            self.received.append(name)
        except (TransportError, ValueError, NotReadyToRead) as exc:
            self.last_error = f"program not stored: {exc}"  # a control's alarm
        if asked:
            self.end.write(XOFF)  # the end of the read-in: the PC's reader stops

    def _punch(self, name: str) -> None:
        try:
            with self.control.store.open(name) as source:
                text = source.read()
        except TransportError as exc:
            self.last_error = f"cannot punch {name}: {exc}"
            return
        self._punch_text(text)

    def _punch_text(self, text: bytes) -> None:
        text = text.strip()
        if not text.startswith(b"%"):
            text = b"%\n" + text
        if not text.endswith(b"%"):
            text += b"\n%"
        self.end.write(_LEADER + text + _LEADER)

    # -- DNC ---------------------------------------------------------------------

    def _feed(self) -> None:
        """Move whole lines from the receive buffer into the control as it has room."""
        c = self.control
        while self._rx:
            if self._dnc_code is None:
                if not self._begin_tape():
                    break
                continue
            if self._rx[0] == self._dnc_code:  # the end of the tape
                del self._rx[0]
                c.end_of_data()
                self._dnc_code = self._dnc_name = None
                continue
            eob = b"\n" if self._dnc_code == ISO_START else bytes([eia.EIA_EOB])
            cut = self._rx.find(eob)
            if cut < 0:
                break
            ahead = c.next_line - 1 - c.running_line
            if c.active and ahead >= self.lookahead_lines:
                break  # the control's memory is full: the line waits in the buffer
            raw = bytes(self._rx[:cut]).translate(None, NOISE).rstrip(b"\r")
            del self._rx[:cut + 1]
            line = eia.decode(raw) if self._dnc_code == EIA_START else raw
            self._run_line(line)
        if self.xoff_sent and len(self._rx) <= self.low_mark_bytes:
            self.end.write(XON)
            self.xoff_sent = False
            self._room = self.buffer_bytes

    def _begin_tape(self) -> bool:
        """Skip to the start of a tape; False when the buffer holds none yet."""
        for offset, byte in enumerate(self._rx):
            if byte in (ISO_START, EIA_START):
                self._dnc_code = byte
                del self._rx[:offset + 1]
                # The rest of the start line (its end of block) is no block.
                eob = b"\n" if byte == ISO_START else bytes([eia.EIA_EOB])
                if self._rx.startswith(b"\r" + eob):
                    del self._rx[:2]
                elif self._rx.startswith(eob):
                    del self._rx[:1]
                return True
        self._rx.clear()  # blank tape before the start
        return False

    def _run_line(self, line: bytes) -> None:
        c = self.control
        if self._dnc_name is None:  # the first block names the run
            self._dnc_name = program_name(line) or "TAPE"
            try:
                c.start_dnc(self._dnc_name, channel=IoChannel.RS232)
            except DncRefused as exc:
                self.last_error = str(exc)
        if c.load(c.next_line, [line]) == 0 and c.active:
            self.last_error = f"line {c.next_line} not taken"

    def _reset(self) -> None:
        self.control.reset()
        self._rx.clear()
        self._dnc_code = self._dnc_name = None
        self._room = self.buffer_bytes
        if self.xoff_sent:
            self.end.write(XON)
            self.xoff_sent = False
