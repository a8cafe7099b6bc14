"""The seed's CNC server side over TCP: file list, download, upload, delete, DNC runs,
and what the operator sends toward the PC: punched programs, READ (QUERY_PUNCH,
QUERY_READ, READ_IN).

One client at a time, as the seed's control: a second connection is answered BUSY and
closed, unless it resumes the DNC run of a client whose link dropped (RESUME_DNC), which
takes the control over. A dropped link leaves a DNC run going for `grace_s`; after that the
control is reset. A bad frame is answered with an ERROR; only a frame that loses the stream
(bad magic, version or length) closes its connection. The server never stops on a client.
It keeps one figure of the link's speed: the longest wait between telling the client the
window has room (GET_FILE_DNC) and the lines arriving (`longest_ask_s`), and counts the
requests it answered, by command (`requests`), so the cost of a client's polling shows.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections import Counter
from io import BytesIO

from worker.simulator.control import (
    Control,
    DncRefused,
    IoChannel,
    Mode,
    NotReadyToRead,
    RunState,
)
from worker.simulator.tcp_link import Aborted, Link, Refused, receive_file, send_file
from worker.transports import dnc_wire as wire
from worker.transports.base import BadPath, Exists, NotFound, TransportError
from worker.transports.dnc_wire import Command, ErrorCode, Frame, HintCode, WireError
from worker.transports.serial_tape import program_name

log = logging.getLogger(__name__)

_STATES = {RunState.IDLE: wire.WireState.IDLE, RunState.WAIT: wire.WireState.WAIT,
           RunState.RUNNING: wire.WireState.RUNNING, RunState.STARVED: wire.WireState.STARVED,
           RunState.DONE: wire.WireState.DONE, RunState.RESET: wire.WireState.RESET}
_HINTS = {"mode": HintCode.NOT_DNC_MODE, "io_channel": HintCode.IO_CHANNEL}
_STORE_ERRORS = {NotFound: ErrorCode.NOT_FOUND, Exists: ErrorCode.EXISTS,
                 BadPath: ErrorCode.BAD_NAME}


class DncServer:
    """Serves one `Control` on a TCP port; `start()` returns at once, `close()` stops it."""

    def __init__(self, control: Control, *, host: str = "127.0.0.1", port: int = 0,
                 heartbeat_s: float = 2.0, ping_checks: int = 3, grace_s: float = 30.0) -> None:
        self.control = control
        self.heartbeat_s = heartbeat_s
        self.ping_checks = ping_checks
        self.grace_s = grace_s
        self._listener = socket.create_server((host, port))
        self.port: int = self._listener.getsockname()[1]
        self._lock = threading.Lock()
        self._active: Link | None = None  # the client that holds the control
        self._run_id = 0  # of the current or last DNC run
        self._orphaned_at: float | None = None  # when a running DNC run lost its client
        self._closed = threading.Event()
        self._asked_at: float | None = None  # when room was last offered, not yet filled
        self.longest_ask_s = 0.0  # the longest wait from room offered to lines received
        self.requests: Counter[Command] = Counter()  # requests answered, by command

    def start(self) -> None:
        threading.Thread(target=self._accept, name="dnc-accept", daemon=True).start()
        threading.Thread(target=self._supervise, name="dnc-heartbeat", daemon=True).start()

    def close(self) -> None:
        self._closed.set()
        self._listener.close()
        with self._lock:
            if self._active is not None:
                self._active.close()

    # -- the operator ----------------------------------------------------------------

    def punch_text(self, data: bytes) -> None:
        """The operator punches a program typed at the control toward the PC: it waits in
        the outbox, named by its first line, until a client takes it (QUERY_PUNCH)."""
        self.control.punch(program_name(data) or "PUNCH", data)

    def request_punch(self, name: str) -> None:
        """The operator punches stored program `name` toward the PC (NotFound if it is not
        stored): it waits in the outbox until a client takes it."""
        with self.control.store.open(name) as source:
            self.control.punch(name, source.read())

    # -- connections ---------------------------------------------------------------

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                sock, _ = self._listener.accept()
            except OSError:
                return  # the listener was closed
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            threading.Thread(target=self._serve, args=(Link(sock),), daemon=True).start()

    def _serve(self, link: Link) -> None:
        try:
            first = True
            while not self._closed.is_set():
                try:
                    frame = wire.read_frame(link.recv_exactly)
                except WireError as exc:
                    link.error(exc.request_id, exc.code, str(exc))
                    if not exc.resync:
                        return
                    continue
                if first and not self._admit(link, frame):
                    return
                first = False
                if self._active is not link:
                    return  # another client took the control over
                try:
                    self._answer(link, frame)
                except WireError:
                    return  # answered already; the stream is lost with that frame
        except (OSError, ConnectionError):
            pass  # the client went away
        except Exception:
            log.exception("dropping a client after an unexpected error")
            with contextlib.suppress(OSError):
                link.error(0, ErrorCode.INTERNAL, "internal error: the connection is closed")
        finally:
            self._release(link)
            link.close()

    def _admit(self, link: Link, frame: Frame) -> bool:
        """Make `link` the active client, or refuse it (BUSY)."""
        with self._lock:
            resumes = frame.command is Command.RESUME_DNC and self._resumable(frame.payload)
            if self._active is None or resumes:
                if self._active is not None:
                    self._active.close()  # the dropped client's half-open connection
                self._active = link
                if resumes:  # only the run's client stops its grace, not any that comes
                    self._orphaned_at = None
                return True
        link.error(frame.request_id, ErrorCode.BUSY, "another client holds the control")
        return False

    def _release(self, link: Link) -> None:
        with self._lock:
            if self._active is link:
                self._active = None
                if self.control.active and self._orphaned_at is None:  # since the run's left
                    self._orphaned_at = time.monotonic()

    def _supervise(self) -> None:
        """Ping checks: a client silent for `heartbeat_s` is pinged; after `ping_checks`
        pings unanswered its link is down. A run without a client is reset after grace_s."""
        while not self._closed.wait(self.heartbeat_s / 2):
            with self._lock:
                link, orphaned_at = self._active, self._orphaned_at
            now = time.monotonic()
            if orphaned_at is not None and now - orphaned_at > self.grace_s:
                log.warning("no client resumed the DNC run within %g s: reset", self.grace_s)
                self.control.reset(ended="abandoned")
                with self._lock:
                    self._orphaned_at = None
            if link is None or now - link.last_heard < self.heartbeat_s:
                continue
            if link.missed_checks >= self.ping_checks:
                log.warning("link down after %d failed ping checks", link.missed_checks)
                link.close()
                continue
            link.missed_checks += 1
            link.last_heard = now  # the next check is one heartbeat from now
            with contextlib.suppress(OSError):
                link.send(Command.KEEP_ALIVE, 0)

    # -- requests ------------------------------------------------------------------

    def _answer(self, link: Link, frame: Frame) -> None:
        handler = _HANDLERS.get(frame.command)
        self.requests[frame.command] += 1
        if frame.command is Command.ERROR:  # the client's answer to a frame of ours
            log.warning("the client refused a frame: %r", frame.payload)
            return  # an answer is never answered, or the two sides would answer forever
        try:
            if handler is None:
                raise Refused(ErrorCode.OUT_OF_SEQUENCE,
                              f"{frame.command.name} is not a request to the control")
            handler(self, link, frame)
        except Aborted:
            pass  # answered OK already
        except WireError as exc:
            link.error(frame.request_id, exc.code, str(exc))
            if not exc.resync:
                raise
        except Refused as exc:
            link.error(frame.request_id, exc.code, str(exc))
        except TransportError as exc:
            code = next((c for kind, c in _STORE_ERRORS.items() if isinstance(exc, kind)),
                        ErrorCode.INTERNAL)
            link.error(frame.request_id, code, str(exc))

    def _keep_alive(self, link: Link, frame: Frame) -> None:
        wire.read_uint(frame.payload, 0)
        if frame.request_id:  # id 0 answers the server's own ping check
            link.send(Command.KEEP_ALIVE, frame.request_id)

    def _file_list(self, link: Link, frame: Frame) -> None:
        wire.read_uint(frame.payload, 0)
        self._send_list(link, frame.request_id)

    def _send_list(self, link: Link, request_id: int) -> None:
        files = [wire.ListedFile(p.name, p.size, p.mtime_s) for p in self.control.store.programs()]
        pages = wire.list_payloads(files)
        for number, page in enumerate(pages, 1):
            more = wire.FLAG_MORE if number < len(pages) else 0
            link.send(Command.SEND_FILE_LIST, request_id, page, more)

    def _get_file(self, link: Link, frame: Frame) -> None:
        name = wire.read_name(frame.payload)
        with self.control.store.open(name) as program:
            size = self.control.store.find(name).size
            send_file(link, frame.request_id, name, size, program.read)

    def _update_file(self, link: Link, frame: Frame) -> None:
        name, size = wire.read_file(frame.payload)
        with self.control.store.receive(name) as out:
            link.send(Command.GET_FILE, frame.request_id, wire.name_payload(name))
            receive_file(link, frame.request_id, name, size, out)
        self._send_list(link, frame.request_id)

    def _delete_file(self, link: Link, frame: Frame) -> None:
        self.control.store.delete(wire.read_name(frame.payload))
        self._send_list(link, frame.request_id)

    def _update_file_dnc(self, link: Link, frame: Frame) -> None:
        name, _total_lines = wire.read_file(frame.payload)
        try:
            self.control.start_dnc(name, channel=IoChannel.NETWORK)
        except DncRefused as exc:
            if exc.reason == "busy":
                raise Refused(ErrorCode.BUSY, str(exc)) from exc
            link.send(Command.HINT, frame.request_id, wire.error_payload(_HINTS[exc.reason],
                                                                         str(exc)))
            return
        with self._lock:
            self._run_id += 1
            self._orphaned_at = None  # the grace of a run left before is not this one's
            link.send(Command.OK, frame.request_id, wire.uint_payload(self._run_id, 4))

    def _query_file_dnc(self, link: Link, frame: Frame) -> None:
        wire.read_uint(frame.payload, 0)
        control = self.control
        if control.mode is not Mode.DNC:  # the seed checks the mode on every query
            link.send(Command.HINT, frame.request_id, wire.error_payload(
                HintCode.NOT_DNC_MODE, f"the control is in {control.mode.value.upper()} mode"))
            return
        self._require_run()
        if control.free_lines == 0:
            link.send(Command.HINT, frame.request_id,
                      wire.error_payload(HintCode.WAIT, "the program window is full"))
            return
        self._send_ready(link, frame.request_id)

    def _send_ready(self, link: Link, request_id: int) -> None:
        free = self.control.free_lines
        payload = wire.ready_payload(self.control.next_line, free)
        if free and self._asked_at is None:
            self._asked_at = time.monotonic()  # the control asks for data from here
        link.send(Command.GET_FILE_DNC, request_id, payload)

    def _send_file_dnc(self, link: Link, frame: Frame) -> None:
        first_line, lines = wire.read_lines(frame.payload)
        if self._asked_at is not None:
            self.longest_ask_s = max(self.longest_ask_s, time.monotonic() - self._asked_at)
            self._asked_at = None
        self._require_run()
        self.control.load(first_line, lines)  # lines it holds already are skipped
        self._send_ready(link, frame.request_id)

    def _send_data(self, link: Link, frame: Frame) -> None:
        parameter = wire.read_uint(frame.payload, 1)
        if parameter not in (wire.SendData.LINE_SYNC, wire.SendData.STOP):
            raise WireError(ErrorCode.BAD_FRAME, f"unknown SEND_DATA parameter {parameter}",
                            resync=True)
        self._require_held_run()
        if parameter == wire.SendData.STOP:
            self.control.reset()
        self._send_position(link, frame.request_id)

    def _end_file_dnc(self, link: Link, frame: Frame) -> None:
        wire.read_uint(frame.payload, 0)
        self._require_held_run()
        self._asked_at = None  # no more data comes: the room offered is not a wait
        self.control.end_of_data()
        self._send_position(link, frame.request_id)

    def _send_position(self, link: Link, request_id: int) -> None:
        control = self.control
        payload = wire.position_payload(control.running_line, control.next_line - 1,
                                        _STATES[control.state])
        link.send(Command.SEND_MAC_POS, request_id, payload)

    def _resume_dnc(self, link: Link, frame: Frame) -> None:
        run_id = wire.read_uint(frame.payload, 4)
        if not self._resumable(frame.payload):
            raise Refused(ErrorCode.NO_RUN, f"the control holds no DNC run {run_id}")
        self._send_ready(link, frame.request_id)

    def _resumable(self, payload: bytes) -> bool:
        """True when RESUME_DNC's `payload` names the last run and it was not reset: a
        done one is resumed too (its client may have been cut before it heard so)."""
        return (payload == wire.uint_payload(self._run_id, 4)
                and self.control.state not in (RunState.IDLE, RunState.RESET))

    def _query_punch(self, link: Link, frame: Frame) -> None:
        wire.read_uint(frame.payload, 0)
        punched = self.control.first_punch()
        if punched is None:
            link.send(Command.HINT, frame.request_id,
                      wire.error_payload(HintCode.WAIT, "nothing punched toward the PC"))
            return
        name, data = punched
        send_file(link, frame.request_id, name, len(data), BytesIO(data).read)
        self.control.punch_sent(punched)  # only once the whole of it went out

    def _query_read(self, link: Link, frame: Frame) -> None:
        wire.read_uint(frame.payload, 0)
        if self.control.ready_to_read:
            link.send(Command.OK, frame.request_id)
        else:
            link.send(Command.HINT, frame.request_id, wire.error_payload(
                HintCode.WAIT, "the control is not ready to read a program in (no READ)"))

    def _read_in(self, link: Link, frame: Frame) -> None:
        name, size = wire.read_file(frame.payload)
        try:
            with self.control.read_in(name) as out:
                link.send(Command.GET_FILE, frame.request_id, wire.name_payload(name))
                receive_file(link, frame.request_id, name, size, out)
        except NotReadyToRead as exc:  # raised before GET_FILE: the client sent nothing
            raise Refused(ErrorCode.OUT_OF_SEQUENCE, str(exc)) from None
        link.send(Command.OK, frame.request_id)

    def _require_run(self) -> None:
        if not self.control.active:
            raise Refused(ErrorCode.NO_RUN, "no DNC run is going on (UPDATE_FILE_DNC first)")

    def _require_held_run(self) -> None:
        """A run that ended (done, reset) is still held: its last position is asked for."""
        if self.control.state is RunState.IDLE:
            raise Refused(ErrorCode.NO_RUN, "the control holds no DNC run (UPDATE_FILE_DNC "
                          "first)")


_HANDLERS = {
    Command.KEEP_ALIVE: DncServer._keep_alive,
    Command.GET_FILE_LIST: DncServer._file_list,
    Command.GET_FILE: DncServer._get_file,
    Command.UPDATE_FILE: DncServer._update_file,
    Command.DELETE_FILE: DncServer._delete_file,
    Command.UPDATE_FILE_DNC: DncServer._update_file_dnc,
    Command.QUERY_FILE_DNC: DncServer._query_file_dnc,
    Command.SEND_FILE_DNC: DncServer._send_file_dnc,
    Command.SEND_DATA: DncServer._send_data,
    Command.END_FILE_DNC: DncServer._end_file_dnc,
    Command.RESUME_DNC: DncServer._resume_dnc,
    Command.QUERY_PUNCH: DncServer._query_punch,
    Command.QUERY_READ: DncServer._query_read,
    Command.READ_IN: DncServer._read_in,
}

