"""The seed protocol's bytes (docs/dnc-protocol.md): frames, commands and payloads.

Used by both sides: the `dnc` transport (client) and the simulator (server). A frame is a
14-byte big-endian header and a payload of at most `MAX_PAYLOAD_BYTES`::

    magic "DQ" | version u8 | command u8 | flags u16 | request id u32 | payload length u32
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import IntEnum

MAGIC = b"DQ"
VERSION = 1
HEADER = struct.Struct(">2sBBHII")
MAX_PAYLOAD_BYTES = 65536  # a longer frame cannot be trusted: the connection is closed
MAX_LINE_BYTES = 4096  # one program line on the wire, without its line ending
FLAG_MORE = 0x0001  # another frame of the same reply follows (a long file list)


class Command(IntEnum):
    """Command codes; the table with who sends what is in docs/dnc-protocol.md."""

    KEEP_ALIVE = 0x01
    ERROR = 0x02
    OK = 0x03
    HINT = 0x04
    GET_FILE_LIST = 0x10
    SEND_FILE_LIST = 0x11
    GET_FILE = 0x12
    SEND_FILE = 0x13
    FILE_DATA = 0x14
    UPDATE_FILE = 0x15
    DELETE_FILE = 0x16
    ABORT_FILE = 0x17
    UPDATE_FILE_DNC = 0x20
    QUERY_FILE_DNC = 0x21
    GET_FILE_DNC = 0x22
    SEND_FILE_DNC = 0x23
    SEND_DATA = 0x24
    SEND_MAC_POS = 0x25
    END_FILE_DNC = 0x26
    RESUME_DNC = 0x27
    QUERY_PUNCH = 0x30
    QUERY_READ = 0x31
    READ_IN = 0x32


class ErrorCode(IntEnum):
    """The code of an ERROR reply."""

    BAD_FRAME = 1  # a payload that does not decode as its command's
    UNKNOWN_COMMAND = 2
    TOO_LONG = 3  # payload length above MAX_PAYLOAD_BYTES
    BAD_VERSION = 4
    NOT_FOUND = 5
    EXISTS = 6
    BAD_NAME = 7
    BUSY = 8  # another client holds the control, or a run is going on
    OUT_OF_SEQUENCE = 9  # a command the current state does not take
    NO_RUN = 10  # no run the command can take (a DNC command, RESUME_DNC of a reset run)
    INTERNAL = 11


class HintCode(IntEnum):
    """The code of a HINT reply: the control cannot do DNC (yet)."""

    WAIT = 0  # not ready (or nothing punched): ask again
    NOT_DNC_MODE = 1
    IO_CHANNEL = 2  # the IO channel is not the network


class SendData(IntEnum):
    """The parameter of SEND_DATA."""

    LINE_SYNC = 0  # answer with the running line
    STOP = 1  # reset the machine, then answer with the running line


class WireState(IntEnum):
    """A DNC run's state in SEND_MAC_POS."""

    IDLE = 0
    WAIT = 1
    RUNNING = 2
    STARVED = 3
    DONE = 4
    RESET = 5


class WireError(Exception):
    """A frame that cannot be taken; `resync` is False when the stream is lost with it."""

    def __init__(self, code: ErrorCode, message: str, *, resync: bool,
                 request_id: int = 0) -> None:
        super().__init__(message)
        self.code = code
        self.resync = resync
        self.request_id = request_id  # of the frame, when its header could be read


@dataclass(frozen=True)
class Frame:
    """One decoded frame; `command` is an int when decoding tolerated an unknown one."""

    command: Command
    request_id: int
    payload: bytes = b""
    flags: int = 0


def encode(command: Command, request_id: int, payload: bytes = b"", flags: int = 0) -> bytes:
    """The bytes of one frame."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes is above {MAX_PAYLOAD_BYTES}")
    return HEADER.pack(MAGIC, VERSION, command, flags, request_id, len(payload)) + payload


def read_frame(recv_exactly: Callable[[int], bytes]) -> Frame:
    """The next frame from a stream; `recv_exactly(n)` returns n bytes or raises.

    Raises WireError: bad magic, version or length lose the stream (resync False); an
    unknown command has had its payload read, so the next frame can follow (resync True).
    """
    magic, version, command, flags, request_id, length = HEADER.unpack(
        recv_exactly(HEADER.size))
    if magic != MAGIC:
        raise WireError(ErrorCode.BAD_FRAME, f"bad magic {magic!r}", resync=False)
    if version != VERSION:
        raise WireError(ErrorCode.BAD_VERSION, f"version {version}, this side speaks "
                        f"{VERSION}", resync=False, request_id=request_id)
    if length > MAX_PAYLOAD_BYTES:
        raise WireError(ErrorCode.TOO_LONG, f"payload length {length} is above "
                        f"{MAX_PAYLOAD_BYTES}", resync=False, request_id=request_id)
    payload = recv_exactly(length) if length else b""
    try:
        known = Command(command)
    except ValueError:
        raise WireError(ErrorCode.UNKNOWN_COMMAND, f"unknown command 0x{command:02x}",
                        resync=True, request_id=request_id) from None
    return Frame(known, request_id, payload, flags)


# -- payload fields -----------------------------------------------------------------


class Fields:
    """Reads a payload's fields in order; any shortfall or leftover is BAD_FRAME."""

    def __init__(self, payload: bytes) -> None:
        self._data = payload
        self._at = 0

    def _take(self, count: int) -> bytes:
        if self._at + count > len(self._data):
            raise WireError(ErrorCode.BAD_FRAME, "payload too short", resync=True)
        part = self._data[self._at:self._at + count]
        self._at += count
        return part

    def uint(self, size: int) -> int:
        return int.from_bytes(self._take(size), "big")

    def blob(self) -> bytes:
        return self._take(self.uint(2))

    def text(self) -> str:
        try:
            return self.blob().decode("utf-8")
        except UnicodeDecodeError:
            raise WireError(ErrorCode.BAD_FRAME, "a name is not UTF-8", resync=True) from None

    def end(self) -> None:
        if self._at != len(self._data):
            raise WireError(ErrorCode.BAD_FRAME, "payload too long for its command",
                            resync=True)


def _blob(data: bytes) -> bytes:
    if len(data) > 0xFFFF:
        raise ValueError("a string field holds at most 65535 bytes")
    return len(data).to_bytes(2, "big") + data


def name_payload(name: str) -> bytes:
    """GET_FILE, DELETE_FILE: a name."""
    return _blob(name.encode("utf-8"))


def read_name(payload: bytes) -> str:
    fields = Fields(payload)
    name = fields.text()
    fields.end()
    return name


def file_payload(name: str, size_or_lines: int) -> bytes:
    """SEND_FILE, UPDATE_FILE, READ_IN (name, bytes) and UPDATE_FILE_DNC (name, lines or
    0)."""
    return name_payload(name) + size_or_lines.to_bytes(8, "big")


def read_file(payload: bytes) -> tuple[str, int]:
    fields = Fields(payload)
    name, size = fields.text(), fields.uint(8)
    fields.end()
    return name, size


@dataclass(frozen=True)
class ListedFile:
    """One entry of SEND_FILE_LIST."""

    name: str
    size: int  # bytes
    mtime_s: int  # POSIX seconds, 0 when unknown


def list_payloads(files: Iterable[ListedFile]) -> list[bytes]:
    """SEND_FILE_LIST pages: each a count u16 and its entries, within MAX_PAYLOAD_BYTES."""
    pages: list[bytes] = []
    page, count = b"", 0
    for entry in files:
        item = name_payload(entry.name) + struct.pack(">QQ", entry.size, entry.mtime_s)
        if count == 0xFFFF or 2 + len(page) + len(item) > MAX_PAYLOAD_BYTES:
            pages.append(count.to_bytes(2, "big") + page)
            page, count = b"", 0
        page, count = page + item, count + 1
    pages.append(count.to_bytes(2, "big") + page)
    return pages


def read_list(payload: bytes) -> list[ListedFile]:
    fields = Fields(payload)
    files = [ListedFile(fields.text(), fields.uint(8), fields.uint(8))
             for _ in range(fields.uint(2))]
    fields.end()
    return files


def error_payload(code: int, message: str) -> bytes:
    """ERROR and HINT: a code u16 and a message."""
    return code.to_bytes(2, "big") + _blob(message.encode("utf-8")[:1024])


def read_error(payload: bytes) -> tuple[int, str]:
    fields = Fields(payload)
    code, message = fields.uint(2), fields.text()
    fields.end()
    return code, message


def lines_payload(first_line: int, lines: list[bytes]) -> bytes:
    """SEND_FILE_DNC: the number of the first line u64, a count u16, the lines."""
    return (first_line.to_bytes(8, "big") + len(lines).to_bytes(2, "big")
            + b"".join(_blob(line) for line in lines))


def lines_fit(lines: list[bytes]) -> int:
    """How many of `lines`, from the first, one SEND_FILE_DNC frame holds."""
    room = MAX_PAYLOAD_BYTES - 10
    for count, line in enumerate(lines):
        room -= 2 + len(line)
        if room < 0 or count == 0xFFFF:
            return count
    return len(lines)


def read_lines(payload: bytes) -> tuple[int, list[bytes]]:
    fields = Fields(payload)
    first = fields.uint(8)
    lines = [fields.blob() for _ in range(fields.uint(2))]
    fields.end()
    if any(len(line) > MAX_LINE_BYTES for line in lines):  # a `line` field's limit
        raise WireError(ErrorCode.BAD_FRAME, f"a line longer than {MAX_LINE_BYTES} bytes",
                        resync=True)
    return first, lines


def ready_payload(next_line: int, free_lines: int) -> bytes:
    """GET_FILE_DNC: the next line the control takes u64, the lines it has room for u32."""
    return struct.pack(">QI", next_line, free_lines)


def read_ready(payload: bytes) -> tuple[int, int]:
    fields = Fields(payload)
    ready = fields.uint(8), fields.uint(4)
    fields.end()
    return ready


def position_payload(running_line: int, lines_loaded: int, state: WireState) -> bytes:
    """SEND_MAC_POS: the running line u64, lines received u64, the run's state u8."""
    return struct.pack(">QQB", running_line, lines_loaded, state)


def read_position(payload: bytes) -> tuple[int, int, WireState]:
    fields = Fields(payload)
    running, loaded, state = fields.uint(8), fields.uint(8), fields.uint(1)
    fields.end()
    try:
        return running, loaded, WireState(state)
    except ValueError:
        raise WireError(ErrorCode.BAD_FRAME, f"unknown run state {state}", resync=True) from None


def uint_payload(value: int, size: int) -> bytes:
    """OK after UPDATE_FILE_DNC and RESUME_DNC (run id u32), SEND_DATA (parameter u8)."""
    return value.to_bytes(size, "big")


def read_uint(payload: bytes, size: int) -> int:
    fields = Fields(payload)
    value = fields.uint(size)
    fields.end()
    return value
