"""The seed protocol's codec: every payload decodes to what was encoded; limits hold."""

from __future__ import annotations

import pytest

from worker.transports import dnc_wire as wire
from worker.transports.dnc_wire import Command, ErrorCode, WireError, WireState


def frames(data: bytes) -> list[wire.Frame]:
    view = memoryview(data)
    at = 0
    found = []

    def exactly(count: int) -> bytes:
        nonlocal at
        part = bytes(view[at:at + count])
        at += count
        return part

    while at < len(data):
        found.append(wire.read_frame(exactly))
    return found


def test_a_frame_round_trips() -> None:
    data = wire.encode(Command.GET_FILE, 5, wire.name_payload("Teil-ä.nc"), wire.FLAG_MORE)
    assert len(data) == wire.HEADER.size + 2 + len("Teil-ä.nc".encode())
    (frame,) = frames(data)
    assert (frame.command, frame.request_id, frame.flags) == (Command.GET_FILE, 5, 1)
    assert wire.read_name(frame.payload) == "Teil-ä.nc"


def test_payloads_round_trip() -> None:
    assert wire.read_file(wire.file_payload("O0001", 2**40)) == ("O0001", 2**40)
    assert wire.read_error(wire.error_payload(ErrorCode.BUSY, "busy")) == (8, "busy")
    assert wire.read_lines(wire.lines_payload(7, [b"G0", b""])) == (7, [b"G0", b""])
    assert wire.read_ready(wire.ready_payload(1001, 100)) == (1001, 100)
    assert wire.read_position(wire.position_payload(5, 9, WireState.DONE)) == (
        5, 9, WireState.DONE)
    assert wire.read_uint(wire.uint_payload(3, 4), 4) == 3


def test_a_long_list_is_split_into_pages_within_the_limit() -> None:
    files = [wire.ListedFile(f"PROGRAM-{n:06d}.NC", n, 0) for n in range(5000)]
    pages = wire.list_payloads(files)
    assert len(pages) > 1 and all(len(p) <= wire.MAX_PAYLOAD_BYTES for p in pages)
    assert [f for p in pages for f in wire.read_list(p)] == files


def test_lines_fit_keeps_a_frame_within_the_limit() -> None:
    lines = [b"x" * 4000] * 40
    count = wire.lines_fit(lines)
    assert len(wire.lines_payload(1, lines[:count])) <= wire.MAX_PAYLOAD_BYTES
    assert len(wire.lines_payload(1, lines[:count + 1])) > wire.MAX_PAYLOAD_BYTES


def test_an_oversize_payload_is_never_encoded() -> None:
    with pytest.raises(ValueError):
        wire.encode(Command.FILE_DATA, 1, bytes(wire.MAX_PAYLOAD_BYTES + 1))


@pytest.mark.parametrize(("data", "code", "resync"), [
    (b"ZZ" + bytes(12), ErrorCode.BAD_FRAME, False),
    (wire.HEADER.pack(wire.MAGIC, 2, 1, 0, 1, 0), ErrorCode.BAD_VERSION, False),
    (wire.HEADER.pack(wire.MAGIC, 1, 1, 0, 1, 2**31), ErrorCode.TOO_LONG, False),
    (wire.HEADER.pack(wire.MAGIC, 1, 0xEE, 0, 1, 0), ErrorCode.UNKNOWN_COMMAND, True),
])
def test_a_bad_header_says_whether_the_stream_survives(
        data: bytes, code: ErrorCode, resync: bool) -> None:
    with pytest.raises(WireError) as bad:
        frames(data)
    assert (bad.value.code, bad.value.resync) == (code, resync)


def test_a_short_or_long_payload_is_bad_frame() -> None:
    with pytest.raises(WireError, match="too short"):
        wire.read_ready(b"\x00")
    with pytest.raises(WireError, match="too long"):
        wire.read_uint(b"\x00\x01", 1)


@pytest.mark.parametrize(("command", "code"), [(Command.QUERY_PUNCH, 0x30),
                                               (Command.QUERY_READ, 0x31)])
def test_the_request_queries_round_trip_empty(command: Command, code: int) -> None:
    data = wire.encode(command, 12)
    assert data[3] == code and len(data) == wire.HEADER.size
    (frame,) = frames(data)
    assert (frame.command, frame.request_id, frame.payload) == (command, 12, b"")
    wire.read_uint(frame.payload, 0)  # empty, as its command's payload must be


def test_read_in_round_trips_its_name_and_size() -> None:
    data = wire.encode(Command.READ_IN, 3, wire.file_payload("O0010", 2**33))
    assert data[3] == 0x32
    (frame,) = frames(data)
    assert frame.command is Command.READ_IN
    assert wire.read_file(frame.payload) == ("O0010", 2**33)
