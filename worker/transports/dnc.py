"""The `dnc` transport: a control's own storage and DNC runs over the seed protocol.

The control's program list is flat: no folders. One connection per transport is kept
across calls (worker.transports.dnc_link), with a heartbeat thread while it is open;
drip-feed runs are in worker.transports.dnc_drip. Machine-initiated requests
(worker.transports.optional.RequestLink) are asked for in polls, each its own exchange:
QUERY_PUNCH for a program the operator punched, QUERY_READ for the control's READ, and
READ_IN sends the answer.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from io import BytesIO
from typing import IO, ClassVar, TypeVar

from worker.transports import dnc_wire as wire
from worker.transports.base import (
    CHUNK_BYTES,
    PART_PREFIX,
    Capabilities,
    Deadline,
    Dropped,
    Entry,
    NoMachineControl,
    NotFound,
    Permanent,
    ProgressFn,
    TransportError,
    Unsupported,
    below_root,
)
from worker.transports.dnc_drip import feed
from worker.transports.dnc_link import DncLink, DncOptions
from worker.transports.dnc_wire import Command, Frame
from worker.transports.drip import DripResult, LineFn, StopFn
from worker.transports.optional import LinkReport

__all__ = ["DncOptions", "DncTransport"]

T = TypeVar("T")
_SPOOL_BYTES = 1024 * 1024  # a program being written is kept in memory up to this, then on disk


class DncTransport(NoMachineControl):
    """Programs of one control; paths are bare program names ("" is the list).

    A model whose root is a folder of its storage (Fanuc's `//CNC_MEM/` is `CNC_MEM`) is
    given it as `roots[0]`: the list is then that folder, the one place the control's
    program memory shows (a model's further roots, a memory card, are not on this link).
    """

    capabilities: ClassVar[Capabilities] = Capabilities(
        folders=False, make_dirs=False, atomic_write=True, drip_feed=True, requests=True)
    own_storage: ClassVar[bool] = True
    server_row: ClassVar[str | None] = None

    def __init__(self, options: DncOptions, *, roots: tuple[str, ...] = ()) -> None:
        self.options = options
        self._root = roots[0].strip("/") if roots else ""
        self._link = DncLink(options)
        self._stop_heartbeat = threading.Event()
        self._heartbeat: threading.Thread | None = None

    def __repr__(self) -> str:
        return f"DncTransport({self.options.host}:{self.options.port})"

    @contextmanager
    def _exchange(self) -> Iterator[DncLink]:
        """The link, connected and held for one exchange; dropped if the exchange broke."""
        with self._link.lock:
            self._link.connect()
            self._start_heartbeat()
            try:
                yield self._link
            except Permanent:
                raise  # a clean refusal: the link is still in step
            except BaseException:
                self._link.close()  # replies may be out of step (or a read was given up)
                raise

    def _start_heartbeat(self) -> None:
        if self._heartbeat is None or not self._heartbeat.is_alive():
            self._heartbeat = threading.Thread(target=self._beat, name="dnc-heartbeat",
                                               daemon=True)
            self._heartbeat.start()

    def _beat(self) -> None:
        while not self._stop_heartbeat.wait(self.options.heartbeat_interval_s / 2):
            self._link.heartbeat()

    def close(self) -> None:
        self._stop_heartbeat.set()
        with self._link.lock:
            self._link.close()

    # -- primitives --------------------------------------------------------------

    def _local(self, path: str) -> str | None:
        return below_root(path, self._root)

    def list_dir(self, path: str) -> list[Entry]:
        local = self._local(path)
        if local is None:
            return [Entry(self._root, True)]
        if local:
            raise NotFound(f"{path}: the control's program list has no folders")
        with self._exchange() as link:
            return _entries(link, link.send(Command.GET_FILE_LIST))

    def stat(self, path: str) -> Entry:
        local = self._local(path)
        name = _name(local or "")
        if not name:
            return Entry(path.strip("/").rsplit("/", 1)[-1], True)
        for entry in self.list_dir(self._root):
            if entry.name == name:
                return entry
        raise NotFound(path)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        name = self._program(path)
        deadline = Deadline(self.options.transfer_timeout_s)
        # The whole file is taken off the link before its first chunk is handed on: the
        # link's lock is a thread's, and a reader may take the chunks on another thread
        # (the API reads the first on the request's, the rest read ahead), whose release
        # of the lock failed and left the machine held for good.
        with tempfile.SpooledTemporaryFile(_SPOOL_BYTES) as spool:
            with self._exchange() as link:
                rid = link.send(Command.GET_FILE, wire.name_payload(name))
                _, size = link.decode(_expect(link.reply(rid), Command.SEND_FILE),
                                      wire.read_file)
                if progress:
                    progress(0, size)
                done = 0
                while done < size:
                    data = _expect(link.reply(rid), Command.FILE_DATA).payload
                    done += len(data)
                    spool.write(data)
                    if progress:
                        progress(done, size)
                    deadline.check(f"read {path}")
                if done != size:  # its frames ran past the size it said: out of step
                    raise Dropped(f"the control sent {done} bytes of {name}, not {size}")
            spool.seek(0)
            while chunk := spool.read(CHUNK_BYTES):
                yield chunk

    def write(self, path: str, chunks: Iterable[bytes], *,
              progress: ProgressFn | None = None) -> int:
        name = self._program(path)
        deadline = Deadline(self.options.transfer_timeout_s)
        with tempfile.SpooledTemporaryFile(_SPOOL_BYTES) as spool:
            size = _spool(chunks, spool)  # the control wants the size first (UPDATE_FILE)
            with self._exchange() as link:
                rid = link.send(Command.UPDATE_FILE, wire.file_payload(name, size))
                _expect(link.reply(rid), Command.GET_FILE)
                _upload(link, rid, name, size, spool.read, progress=progress,
                        deadline=deadline, what=f"write {path}")
                _entries(link, rid)  # the updated list: the program is stored
        return size

    def delete(self, path: str) -> None:
        name = self._program(path)
        with self._exchange() as link:
            _entries(link, link.send(Command.DELETE_FILE, wire.name_payload(name)))

    def _program(self, path: str) -> str:
        name = _name(self._local(path) or "")
        if not name:
            raise NotFound(f"{path}: not a program")
        return name

    def make_dir(self, path: str) -> None:
        raise Unsupported("the control's program list has no folders")

    def remove_dir(self, path: str) -> None:
        raise Unsupported("the control's program list has no folders")

    # -- link state ----------------------------------------------------------------

    def link_report(self) -> LinkReport:
        """One KEEP_ALIVE and its round trip (worker.transports.optional.LinkReporter).

        The protocol has no message that asks the control for its mode (DNC, MEM, EDIT):
        a control says it only when it refuses a run, so the report leaves it out.
        """
        started = time.perf_counter()
        try:
            with self._exchange() as link:
                link.ping()
        except TransportError as exc:
            return LinkReport(heartbeat=False, round_trip_ms=None, error=str(exc))
        return LinkReport(heartbeat=True,
                          round_trip_ms=round((time.perf_counter() - started) * 1000, 2))

    # -- machine-initiated requests (worker.transports.optional.RequestLink) ------------

    def connect(self) -> None:
        """Connect to the control now (the control keeps what is punched until asked)."""
        with self._exchange():
            pass

    def receive_program(self, *, timeout_s: float) -> bytes | None:
        """The oldest program the operator punched that the control holds (QUERY_PUNCH,
        asked every `poll_interval_s`); None when none came within `timeout_s`.

        Raises:
            Permanent: the program is longer than `max_receive_bytes`; it was read to its
                end and dropped, so the control let go of it and the link is in step.
        """
        return self._until(timeout_s, self._punched)

    def _punched(self, link: DncLink) -> bytes | None:
        rid = link.send(Command.QUERY_PUNCH)
        reply = link.reply(rid)
        if reply.command is Command.HINT:
            return None  # nothing punched yet
        name, size = link.decode(_expect(reply, Command.SEND_FILE), wire.read_file)
        limit = self.options.max_receive_bytes
        deadline = Deadline(self.options.transfer_timeout_s)
        data = bytearray()
        done = 0
        while done < size:
            piece = _expect(link.reply(rid), Command.FILE_DATA).payload
            done += len(piece)
            if size <= limit:
                data += piece  # one too long is read to its end only: the link stays in step
            deadline.check(f"the program {name} punched")
        if done != size:
            raise Dropped(f"the control sent {done} bytes of {name}, not {size}")
        if size > limit:
            raise Permanent(f"the program {name} punched is {size} bytes, longer than "
                            f"{limit} (max_receive_bytes): discarded")
        return bytes(data)

    def wait_ready_to_read(self, *, timeout_s: float) -> bool:
        """True once the control answers QUERY_READ with OK (its operator pressed READ),
        asked every `poll_interval_s`; False when `timeout_s` passed first."""
        return bool(self._until(timeout_s, _ready))

    def send_to_read(self, name: str, data: bytes) -> None:
        """READ_IN: `data` as it is, stored by the control under `name` replacing its
        namesake (BadPath for a name it cannot take; refused, Permanent, when it is not
        ready to read)."""
        deadline = Deadline(self.options.transfer_timeout_s)
        with self._exchange() as link:
            rid = link.send(Command.READ_IN, wire.file_payload(name, len(data)))
            _expect(link.reply(rid), Command.GET_FILE)
            _upload(link, rid, name, len(data), BytesIO(data).read, progress=None,
                    deadline=deadline, what=f"send {name} to be read in")
            _expect(link.reply(rid), Command.OK)  # read in: stored

    def _until(self, timeout_s: float, ask: Callable[[DncLink], T | None]) -> T | None:
        """`ask` once per `poll_interval_s` until it answers or `timeout_s` passes; the
        link is held for each ask only, so the heartbeat and other uses go on between."""
        ends = time.monotonic() + timeout_s
        while True:
            with self._exchange() as link:
                answer = ask(link)
            left_s = ends - time.monotonic()
            if answer is not None or left_s <= 0:
                return answer
            time.sleep(min(self.options.poll_interval_s, left_s))

    # -- drip feed -----------------------------------------------------------------

    def drip_feed(self, name: str, lines: Iterable[bytes], *, total_lines: int | None,
                  on_line: LineFn, should_stop: StopFn) -> DripResult:
        """Run `name` from `lines` on the control (worker.transports.drip.DripFeeder)."""
        with self._link.lock:
            self._start_heartbeat()
            return feed(self._link, name, lines, total_lines=total_lines, on_line=on_line,
                        should_stop=should_stop)


def _name(path: str) -> str:
    """The program name of `path`; NotFound for a path into a folder (there are none)."""
    name = path.strip("/")
    if "/" in name or name.startswith(PART_PREFIX):
        raise NotFound(f"{path}: the control's program list has no folders")
    return name


def _expect(frame: Frame, command: Command) -> Frame:
    if frame.command is not command:
        raise Dropped(f"the control answered {frame.command.name}, not {command.name}")
    return frame


def _entries(link: DncLink, request_id: int) -> list[Entry]:
    """The pages of a SEND_FILE_LIST reply, as entries."""
    entries: list[Entry] = []
    while True:
        frame = _expect(link.reply(request_id), Command.SEND_FILE_LIST)
        entries += [Entry(f.name, False, f.size, float(f.mtime_s) or None)
                    for f in link.decode(frame, wire.read_list)]
        if not frame.flags & wire.FLAG_MORE:
            return entries


def _ready(link: DncLink) -> bool | None:
    """True when the control is ready to read a program in; None when not yet."""
    reply = link.request(Command.QUERY_READ)
    if reply.command is Command.HINT:
        return None
    _expect(reply, Command.OK)
    return True


def _upload(link: DncLink, request_id: int, name: str, size: int,
            read: Callable[[int], bytes], *, progress: ProgressFn | None, deadline: Deadline,
            what: str) -> None:
    """SEND_FILE and the FILE_DATA frames of an upload, after the control's GET_FILE."""
    link.send(Command.SEND_FILE, wire.file_payload(name, size), request_id=request_id)
    done = 0
    while data := read(wire.MAX_PAYLOAD_BYTES):
        link.send(Command.FILE_DATA, data, request_id=request_id)
        done += len(data)
        if progress:
            progress(done, size)
        deadline.check(what)


def _spool(chunks: Iterable[bytes], spool: IO[bytes]) -> int:
    size = 0
    for chunk in chunks:
        spool.write(chunk)
        size += len(chunk)
    spool.seek(0)
    return size
