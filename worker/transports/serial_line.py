"""The `serial` transport: a machine reached over an RS-232 line (pyserial URLs).

A serial line has no directory, so the file primitives work on what dncq holds for the
machine, kept in the transport's state folder (`<data_dir>/serial/<machine>/programs`):

- `write` punches the program to the machine (the operator has put the control in
  receive: EDIT, read-in) and, once the whole program went out, keeps it as dncq's copy
  under the name; never overwrites a copy. The copy is the bytes given; the punch is
  its lines, framed, in the line's code and end of line.
- `receive_punch` waits for a program the operator punches from the control and stores
  it under the name the control gives it (its O-number, else its first word), replacing
  an older punch of that name: what the machine last punched is its truth.
- `list_dir("")`, `stat` and `read` show those programs: what the machine punched plus
  what dncq sent it. A backup of such a machine is that.
- `delete` forgets dncq's copy; the control's memory is out of reach of the line, so it
  is not touched. It is not Unsupported: without it a stale copy could never be
  dropped from what dncq holds, and from every backup after.
- No folders (`folders`, `make_dirs` off).

Machine-initiated requests (`requests`, worker.transports.optional.RequestLink): the
operator punches a request program (`receive_program`, kept nowhere); the operator
switches the control to read in and presses READ, which a control with DC codes on says
with a DC1 (`wait_ready_to_read`); the answer is punched as `write` punches it, without
a copy (`send_to_read`).

Drip-feed (`drip_feed`): the leader, the start character and an end of line, then the
lines, each with the end of line, then the end character and the trailer (a program's
own first `%` line and last `%` line are that frame: not sent twice). The machine's
XON/XOFF (DC3 holds, DC1 releases) or RTS/CTS pauses the sender; see `serial_port`. The
running line reported is the last line whose every character was written to the line,
at the line's pace, while the machine was not holding it: flow control let it through.
A control buffers what it got, so the line it executes trails that by at most its
buffer. A hold longer than `send_timeout_s` (or a port that fails) ends the run with
`LinkLost` and that line. Stop: nothing more of the program is sent; after the last whole
line (a line stopped during a hold is finished first: a control never holds a part of a
block), the end character and the trailer follow (the control takes it as the end of the
tape, runs out what it holds and ends), once the control takes characters again if it
held the line; a hold longer than `send_timeout_s` leaves it there (the line is not the
machine's to take; its operator resets it).
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO, ClassVar

from worker.transports import eia
from worker.transports.base import (
    CHUNK_BYTES,
    BadPath,
    Capabilities,
    Entry,
    Exists,
    NoMachineControl,
    NotFound,
    Permanent,
    ProgressFn,
    PunchedInstead,
    TimedOut,
    TransportError,
    Unsupported,
    below_root,
)
from worker.transports.drip import DripResult, LineFn, LinkLost, StopFn
from worker.transports.serial_options import SerialOptions
from worker.transports.serial_port import Line
from worker.transports.serial_receive import punch_start, take_punch
from worker.transports.serial_tape import (
    DC1,
    lines_of,
    own_framing_marked,
    program_body,
    program_name,
)

__all__ = ["SerialOptions", "SerialTransport"]

_PART = ".part-"  # copies being written: never listed
_PUNCH_BLOCK_BYTES = 4096  # lines sent together in a write: fewer, larger writes


class SerialTransport(NoMachineControl):
    """A machine on an RS-232 line, and the programs dncq holds for it."""

    capabilities: ClassVar[Capabilities] = Capabilities(
        folders=False, make_dirs=False, drip_feed=True, requests=True,
        held_copies=True)
    own_storage: ClassVar[bool] = True
    server_row: ClassVar[str | None] = None

    def __init__(self, options: SerialOptions, *, folder: Path,
                 roots: tuple[str, ...] = ()) -> None:
        """Args:
        options: the machine's options from the fleet file.
        folder: the transport's state folder for this machine.
        roots: the model's storage roots: the copies show in the first (Fanuc's CNC_MEM).
        """
        self.options = options
        self._root = roots[0] if roots else ""
        self.programs = folder / "programs"
        self.programs.mkdir(parents=True, exist_ok=True, mode=0o700)
        self._line: Line | None = None  # opened on first use, kept until close()
        self._lock = threading.Lock()  # one use of the line at a time

    # -- the line ----------------------------------------------------------------

    def _open(self) -> Line:
        if self._line is None:
            self._line = Line(self.options)
        return self._line

    def connect(self) -> None:
        """Open the line now, so that a punch the operator starts next is not missed."""
        with self._lock:
            self._open()

    def _forget_line(self) -> None:
        """After a failure: the next use opens the line again."""
        if self._line is not None:
            self._line.close()
            self._line = None

    def _encoded(self, text: bytes) -> bytes:
        return eia.encode(text) if self.options.code == "eia" else text

    def _frame(self, char: str) -> bytes:
        return self._encoded(char.encode("ascii"))

    # -- dncq's copies -----------------------------------------------------------

    def _copy(self, path: str) -> Path:
        """The copy's file; NotFound for a path into a folder (there are none)."""
        path = below_root(path, self._root) or ""
        if not path or "/" in path or path in (".", ".."):
            raise NotFound(path)
        if path.startswith("."):
            raise BadPath(f"a program name cannot start with '.': {path!r}")
        if len(path.encode()) > 255:
            raise BadPath(f"program name longer than 255 bytes: {path!r}")
        return self.programs / path

    def list_dir(self, path: str) -> list[Entry]:
        local = below_root(path, self._root) if path != "." else ""
        if local is None:
            return [Entry(self._root, True)]
        if local:
            raise NotFound(path)
        entries = []
        for item in os.scandir(self.programs):
            if not item.name.startswith(".") and item.is_file(follow_symlinks=False):
                st = item.stat(follow_symlinks=False)
                entries.append(Entry(item.name, False, st.st_size, st.st_mtime))
        return sorted(entries, key=lambda e: e.name)

    def stat(self, path: str) -> Entry:
        if not below_root(path, self._root):
            return Entry(path.strip("/").rsplit("/", 1)[-1], True)
        try:
            st = self._copy(path).lstat()
        except FileNotFoundError:
            raise NotFound(path) from None
        return Entry(path, False, st.st_size, st.st_mtime)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        try:
            source = self._copy(path).open("rb")
        except FileNotFoundError:
            raise NotFound(path) from None
        total = os.fstat(source.fileno()).st_size
        return _chunks(source, total, progress)

    def delete(self, path: str) -> None:
        try:
            self._copy(path).unlink()
        except FileNotFoundError:
            raise NotFound(path) from None

    def make_dir(self, path: str) -> None:
        raise Unsupported("a serial line has no folders")

    def remove_dir(self, path: str) -> None:
        raise Unsupported("a serial line has no folders")

    def write(self, path: str, chunks: Iterable[bytes], *,
              progress: ProgressFn | None = None) -> int:
        final = self._copy(path)
        if final.exists():
            raise Exists(path)
        part = self.programs / f"{_PART}{uuid.uuid4().hex}"
        try:
            size = 0
            with part.open("wb") as out:  # the whole program first: a source that breaks
                for chunk in chunks:     # midway punches nothing
                    out.write(chunk)
                    size += len(chunk)
                    if progress is not None:
                        progress(size, None)
            with part.open("rb") as source:
                self._punch(lines_of(iter(lambda: source.read(CHUNK_BYTES), b"")))
            try:
                os.link(part, final)  # fails if the name was taken meanwhile: no overwrite
            except FileExistsError:
                raise Exists(path) from None
            return size
        finally:
            part.unlink(missing_ok=True)

    def _punch(self, lines: Iterator[bytes]) -> None:
        o = self.options
        start, end = o.program_start.encode(), o.program_end.encode()
        with self._lock:
            line = self._open()
            try:
                line.discard_input()
                block = bytearray(b"\0" * o.leader_nulls)
                if o.framing:
                    block += self._encoded(start + o.eol)
                body = program_body(lines, start=start, end=end) if o.framing else lines
                for text in body:
                    block += self._encoded(text + o.eol)
                    if len(block) >= _PUNCH_BLOCK_BYTES:
                        line.send(bytes(block))
                        block.clear()
                if o.framing:
                    block += self._encoded(end)
                block += b"\0" * o.trailer_nulls
                line.send(bytes(block))
                line.drain()
            except TransportError:
                self._forget_line()
                raise

    # -- what the machine punches ------------------------------------------------

    def receive_punch(self, *, timeout_s: float) -> Entry:
        """Wait up to `timeout_s` for a program punched from the control, store it and
        return its entry.

        Raises:
            TimedOut: nothing came in `timeout_s`, or the punch stopped for longer than
                `receive_timeout_s` before its end character.
        """
        text = self._receive(timeout_s, max_bytes=None)
        if text is None:
            raise TimedOut(f"no program punched within {timeout_s:g} s")
        name = program_name(text) or time.strftime("PUNCH-%Y%m%d-%H%M%S")
        final = self._copy(name)
        part = self.programs / f"{_PART}{uuid.uuid4().hex}"
        part.write_bytes(text)
        os.replace(part, final)  # the machine's latest punch of that name wins
        return self.stat(name)

    def _receive(self, timeout_s: float, *, max_bytes: int | None) -> bytes | None:
        with self._lock:
            line = self._open()
            line.flow_in = False  # the machine's data is no flow control
            try:
                return take_punch(line, self.options, timeout_s=timeout_s,
                                  max_bytes=max_bytes)
            except Permanent:
                raise  # read to its end and dropped: the line is in step
            except TransportError:
                self._forget_line()
                raise
            finally:
                line.flow_in = True

    # -- machine-initiated requests (worker.transports.optional.RequestLink) --------------

    def receive_program(self, *, timeout_s: float) -> bytes | None:
        """The next program the operator punches, kept nowhere (see RequestLink); one
        longer than `max_receive_bytes` is refused (Permanent)."""
        return self._receive(timeout_s, max_bytes=self.options.max_receive_bytes)

    def wait_ready_to_read(self, *, timeout_s: float) -> bool:
        """True once the control says it reads (`ready_signal`): a DC1 it sent since the
        line was last used counts. A program it begins to punch first ends the wait
        (PunchedInstead) and stays on the line for `receive_program`: the operator sent
        something else rather than read the answer, and it must not be lost. Anything else
        the control sends is ignored."""
        o = self.options
        if o.ready_signal == "none":
            time.sleep(min(o.ready_delay_s, timeout_s))  # the operator's time to press READ
            return o.ready_delay_s <= timeout_s
        ends = time.monotonic() + timeout_s
        with self._lock:
            line = self._open()
            line.flow_in = False  # here a DC1 is the signal, not the release of a hold
            try:
                while (left_s := ends - time.monotonic()) > 0:
                    raw = line.read_some(left_s)
                    ready, punched = raw.find(DC1), punch_start(o, raw)
                    if punched >= 0 and not 0 <= ready < punched:
                        line.put_back(raw[punched:])
                        raise PunchedInstead("the control punched a program instead of "
                                             "reading the answer in")
                    if ready >= 0:
                        return True
                return False
            except PunchedInstead:
                raise  # the line is good, and holds the program's start
            except TransportError:
                self._forget_line()
                raise
            finally:
                line.flow_in = True

    def send_to_read(self, name: str, data: bytes) -> None:
        """Punch `data` to the control, framed as `write` punches; no copy, never Exists.
        `name` is not on the tape: the control names the program by its first line."""
        self._punch(lines_of([data]))

    # -- drip-feed ---------------------------------------------------------------

    def drip_feed(self, name: str, lines: Iterable[bytes], *, total_lines: int | None,
                  on_line: LineFn, should_stop: StopFn) -> DripResult:
        o = self.options
        sent = 0
        with self._lock:
            line = self._open()
            try:
                line.discard_input()
                head = b"\0" * o.leader_nulls
                if o.framing:
                    head += self._frame(o.program_start) + self._encoded(o.eol)
                line.send(head)
                marked = own_framing_marked(lines, start=o.program_start.encode(),
                                            end=o.program_end.encode()) if o.framing \
                    else iter(lines)
                for text in marked:  # None: the program's own `%`, sent once as the frame
                    if should_stop():
                        return self._stopped(line, sent)
                    if text is not None and not line.send(self._encoded(text + o.eol),
                                                          should_stop):
                        # Stopped while the control held the line: the block goes whole
                        # (none or a part of it went), then the end of the tape.
                        return self._stopped(line, sent, rest=line.unsent)
                    sent += 1
                    on_line(sent, sent)
                line.send(self._tail())
                line.drain()
            except TransportError as exc:
                self._forget_line()
                raise LinkLost(f"{name}: {exc}", last_line=sent, lines_sent=sent) from exc
        return DripResult(lines_sent=sent, last_line=sent, stopped=False)

    def _tail(self) -> bytes:
        o = self.options
        return (self._frame(o.program_end) if o.framing else b"") + b"\0" * o.trailer_nulls

    def _stopped(self, line: Line, sent: int, *, rest: bytes | None = None) -> DripResult:
        """The end of the tape after the last whole line: `rest`, what is left of a line
        stopped during a hold, goes first, so that the control never holds a part of a
        block (both wait up to `send_timeout_s` for a control that holds the line)."""
        try:
            if rest is not None:
                line.send(rest)
                sent += 1
            line.send(self._tail())
            line.drain()
            return DripResult(lines_sent=sent, last_line=sent, stopped=True, stop_said=(
                "the end of the tape was sent: the control runs out the blocks it holds"))
        except TransportError:
            self._forget_line()  # the run is over either way: the stop was asked for
        # A line cannot reset a control: its operator does.
        return DripResult(lines_sent=sent, last_line=sent, stopped=True, stop_said=(
            "the control held the line past send_timeout_s, so the end of the tape could not "
            "be sent: reset it at the machine before the next run"))

    def close(self) -> None:
        with self._lock:
            self._forget_line()


def _chunks(source: BinaryIO, total: int, progress: ProgressFn | None) -> Iterator[bytes]:
    done = 0
    with source:
        while chunk := source.read(CHUNK_BYTES):
            done += len(chunk)
            if progress is not None:
                progress(done, total)
            yield chunk
    if progress is not None and total == 0:
        progress(0, 0)
