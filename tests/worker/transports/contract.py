"""The conformance suite every transport passes.

A transport's test module imports everything from here and supplies one fixture,
`transport`: a connected transport on an empty storage of a real server, whose top
("" for the transport) is writable, closed after the test. Capabilities the transport
declares off (folders) are checked to be refused.

    from tests.worker.transports.contract import *  # noqa: F403

    @pytest.fixture
    def transport(ftp_server): ...
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator

import pytest

from worker.transports.base import (
    Entry,
    Exists,
    NotEmpty,
    NotFound,
    Transport,
    TransportError,
    Unsupported,
    first_chunk_then,
)


def put(t: Transport, path: str, data: bytes) -> int:
    return t.write(path, iter([data[i:i + 65536] for i in range(0, len(data), 65536)] or [b""]))


def get(t: Transport, path: str) -> bytes:
    return b"".join(t.read(path))


def names(entries: list[Entry]) -> set[str]:
    return {e.name for e in entries}


def test_write_then_read_gives_the_same_bytes(transport: Transport) -> None:
    data = bytes(range(256)) * 1000 + b"\r\n%\n"
    assert put(transport, "P1.nc", data) == len(data)
    assert get(transport, "P1.nc") == data


def test_an_empty_file_round_trips(transport: Transport) -> None:
    put(transport, "EMPTY.nc", b"")
    assert get(transport, "EMPTY.nc") == b""
    assert transport.stat("EMPTY.nc").size in (0, None)


def test_a_large_file_streams_through_intact(transport: Transport) -> None:
    chunk = hashlib.sha256(b"seed").digest() * 8192  # 256 KiB
    size = 0
    digest = hashlib.sha256()

    def chunks() -> Iterator[bytes]:
        nonlocal size
        for _ in range(24):  # 6 MiB
            size += len(chunk)
            digest.update(chunk)
            yield chunk

    transport.write("BIG.bin", chunks())
    back = hashlib.sha256()
    for part in transport.read("BIG.bin"):
        back.update(part)
    assert back.hexdigest() == digest.hexdigest()


def test_write_never_overwrites(transport: Transport) -> None:
    put(transport, "P1.nc", b"first")
    with pytest.raises(Exists):
        put(transport, "P1.nc", b"second")
    assert get(transport, "P1.nc") == b"first"


def test_a_write_that_fails_midway_leaves_nothing_under_the_name(transport: Transport) -> None:
    def chunks() -> Iterator[bytes]:
        yield b"x" * 100_000
        raise TransportError("the source broke")

    with pytest.raises(TransportError):
        transport.write("HALF.nc", chunks())
    with pytest.raises(NotFound):
        transport.stat("HALF.nc")
    assert "HALF.nc" not in names(transport.list_dir(""))


def test_list_dir_shows_files_and_folders(transport: Transport) -> None:
    put(transport, "A.nc", b"a")
    if transport.capabilities.make_dirs:
        transport.make_dir("SUB")
    entries = {e.name: e for e in transport.list_dir("")}
    assert not entries["A.nc"].is_dir
    if transport.capabilities.make_dirs:
        assert entries["SUB"].is_dir


def test_stat_gives_the_size(transport: Transport) -> None:
    put(transport, "S.nc", b"12345")
    entry = transport.stat("S.nc")
    assert entry.name == "S.nc" and not entry.is_dir and entry.size in (5, None)


def test_missing_things_are_not_found(transport: Transport) -> None:
    with pytest.raises(NotFound):
        transport.stat("NOPE.nc")
    with pytest.raises(NotFound):
        first_chunk_then(iter(transport.read("NOPE.nc")))
    with pytest.raises(NotFound):
        transport.delete("NOPE.nc")
    with pytest.raises(NotFound):
        transport.list_dir("NODIR")


def test_delete_removes_the_file(transport: Transport) -> None:
    put(transport, "D.nc", b"d")
    transport.delete("D.nc")
    with pytest.raises(NotFound):
        transport.stat("D.nc")


def test_folders_are_made_and_removed_where_the_transport_says_it_can(
        transport: Transport) -> None:
    """Where it can: a folder is made, used, refused when it is there or not empty, and
    removed. Where its capabilities say it cannot (a control's program list, a serial
    line), both steps are refused as Unsupported and no folder appears."""
    if not transport.capabilities.make_dirs:
        for step in (transport.make_dir, transport.remove_dir):
            with pytest.raises(Unsupported):
                step("F")
        assert "F" not in names(transport.list_dir(""))
        return
    transport.make_dir("F")
    with pytest.raises(Exists):
        transport.make_dir("F")
    transport.make_dir("F/G")
    put(transport, "F/G/P.nc", b"p")
    assert get(transport, "F/G/P.nc") == b"p"
    assert names(transport.list_dir("F")) == {"G"}
    with pytest.raises(NotEmpty):
        transport.remove_dir("F")
    transport.delete("F/G/P.nc")
    transport.remove_dir("F/G")
    transport.remove_dir("F")
    assert "F" not in names(transport.list_dir(""))


def test_writing_into_a_missing_folder_is_not_found(transport: Transport) -> None:
    with pytest.raises(NotFound):
        put(transport, "NODIR/P.nc", b"p")


def test_non_ascii_names_round_trip(transport: Transport) -> None:
    put(transport, "Teil-ä.nc", b"x")
    assert "Teil-ä.nc" in names(transport.list_dir(""))
    assert get(transport, "Teil-ä.nc") == b"x"


def test_progress_is_reported_while_reading(transport: Transport) -> None:
    put(transport, "PR.nc", b"y" * 300_000)
    seen: list[int] = []
    b"".join(transport.read("PR.nc", progress=lambda done, total: seen.append(done)))
    assert seen and seen[-1] == 300_000


__all__ = [name for name in dir() if name.startswith("test_")]  # what `import *` brings
