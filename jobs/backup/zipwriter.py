"""A streaming ZIP writer for members deflated (or stored) before they reach it.

Backups deflate each file while fetching it (the workers, for a stored backup and for
backupFiles alike), so writing the ZIP only copies bytes; stream-zip and
zipstream-ng cannot take pre-compressed members. Sizes and CRC are known
up front, so local headers carry them (no data descriptor). Layout, per PKWARE APPNOTE
6.3.10: 4.3.7 local file header, 4.3.12 central directory header, 4.5.3 ZIP64 extended
information extra field (a member whose sizes, or whose local-header offset, do not fit
in 32 bits), 4.3.14/4.3.15 ZIP64 end of central directory record and locator (more than
65,535 entries, or a central directory past 4 GiB), 4.3.16 end of central directory.
Names are flagged UTF-8 (4.4.4 bit 11); times are DOS times in UTC, clamped to 1980,
plus the extended timestamp extra field (4.5.7, "UT"). The first member should be a
directory entry: at offset 0 it is never ZIP64 (macOS Archive Utility mishandles a ZIP
whose first member is).
"""

from __future__ import annotations

import stat
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime

STORED, DEFLATED = 0, 8  # compression methods (4.4.5)
UTF8_FLAG = 0x0800
MAX_32 = 0xFFFFFFFF  # a 32-bit field at this value means "see the ZIP64 extra field"
MAX_16 = 0xFFFF
_VERSION_MADE_BY = (3 << 8) | 63  # Unix attributes, APPNOTE 6.3
_VERSION_DEFAULT, _VERSION_ZIP64 = 20, 45
_FILE_ATTRIBUTES = (stat.S_IFREG | 0o644) << 16
_DIR_ATTRIBUTES = (stat.S_IFDIR | 0o755) << 16 | 0x10  # 0x10: the MS-DOS directory bit
_ZIP_EPOCH = datetime(1980, 1, 1, tzinfo=UTC)  # the first time a DOS date holds
_DOS_END = datetime(2107, 12, 31, 23, 59, 58, tzinfo=UTC)  # the last time a DOS date holds
_LOCAL = struct.Struct("<IHHHHHIIIHH")
_CENTRAL = struct.Struct("<IHHHHHHIIIHHHHHII")
_ZIP64_END = struct.Struct("<IQHHIIQQQQ")
_ZIP64_LOCATOR = struct.Struct("<IIQI")
_END = struct.Struct("<IHHHHIIH")
_CENTRAL_BATCH = 1024  # central headers joined per yielded chunk


@dataclass(frozen=True)
class PreparedMember:
    """One entry: a folder (name ending in /) or a file whose bytes are already compressed.

    `chunks` hold `compressed_size` bytes of raw deflate (method 8, no zlib header) or the
    plain bytes (method 0); `crc32` and `size` are those of the plain bytes.
    """

    name: str
    modified: datetime
    crc32: int = 0
    compressed_size: int = 0
    size: int = 0
    method: int = STORED
    chunks: Iterable[bytes] = ()

    @property
    def is_dir(self) -> bool:
        return self.name.endswith("/")


def deflated(name: str, modified: datetime, data: bytes, *, level: int) -> PreparedMember:
    """A file member from bytes in memory (a manifest), raw-deflated at `level`."""
    deflater = zlib.compressobj(level, zlib.DEFLATED, -zlib.MAX_WBITS)
    body = deflater.compress(data) + deflater.flush()
    return PreparedMember(name, modified, zlib.crc32(data), len(body), len(data), DEFLATED,
                          [body])


def write_zip(members: Iterable[PreparedMember]) -> Iterator[bytes]:
    """The ZIP of `members`, as chunks; raises ValueError if a member's bytes disagree."""
    offset = 0
    central: list[bytes] = []
    for m in members:
        name = m.name.encode("utf-8")
        dos_time, dos_date, unix_time = _times(m.modified)
        method = STORED if m.is_dir else m.method
        if method not in (STORED, DEFLATED):
            raise ValueError(f"{m.name}: compression method {method} is not supported")
        big = not m.is_dir and max(m.size, m.compressed_size) >= MAX_32
        local_extra = unix_time
        if big:  # 4.5.3: the local header's ZIP64 field holds both sizes
            local_extra += struct.pack("<HHQQ", 0x0001, 16, m.size, m.compressed_size)
        header = _LOCAL.pack(
            0x04034B50, _VERSION_ZIP64 if big else _VERSION_DEFAULT, UTF8_FLAG, method,
            dos_time, dos_date, m.crc32, MAX_32 if big else m.compressed_size,
            MAX_32 if big else m.size, len(name), len(local_extra))
        yield header + name + local_extra
        written = 0
        for chunk in m.chunks:
            written += len(chunk)
            yield chunk
        if written != m.compressed_size:
            raise ValueError(f"{m.name}: {written} bytes, {m.compressed_size} announced")
        # 4.5.3: the central field holds only the values whose 32-bit fields are 0xFFFFFFFF.
        wide = [m.size, m.compressed_size] if big else []
        if offset >= MAX_32:
            wide.append(offset)
        central_extra = unix_time
        if wide:
            central_extra += struct.pack(f"<HH{len(wide)}Q", 0x0001, 8 * len(wide), *wide)
        central.append(_CENTRAL.pack(
            0x02014B50, _VERSION_MADE_BY, _VERSION_ZIP64 if wide else _VERSION_DEFAULT,
            UTF8_FLAG, method, dos_time, dos_date, m.crc32, min(m.compressed_size, MAX_32),
            min(m.size, MAX_32), len(name), len(central_extra), 0, 0, 0,
            _DIR_ATTRIBUTES if m.is_dir else _FILE_ATTRIBUTES, min(offset, MAX_32),
        ) + name + central_extra)
        offset += len(header) + len(name) + len(local_extra) + written
    directory_offset, directory_size = offset, 0
    for start in range(0, len(central), _CENTRAL_BATCH):
        batch = b"".join(central[start:start + _CENTRAL_BATCH])
        directory_size += len(batch)
        yield batch
    entries = len(central)
    end_offset = directory_offset + directory_size
    if entries >= MAX_16 or directory_offset >= MAX_32 or directory_size >= MAX_32:
        yield _ZIP64_END.pack(0x06064B50, _ZIP64_END.size - 12, _VERSION_MADE_BY,
                              _VERSION_ZIP64, 0, 0, entries, entries, directory_size,
                              directory_offset)
        yield _ZIP64_LOCATOR.pack(0x07064B50, 0, end_offset, 1)
    yield _END.pack(0x06054B50, 0, 0, min(entries, MAX_16), min(entries, MAX_16),
                    min(directory_size, MAX_32), min(directory_offset, MAX_32), 0)


def joined(chunks: Iterable[bytes], size: int) -> Iterator[bytes]:
    """The chunks gathered into pieces of at least `size` bytes (the last may be shorter).

    `write_zip` yields a member's header and its bytes apart, two or more pieces of a few
    KB for each program; a server that sends each piece on its own (a streamed answer:
    one hand-over between threads and one write each) spent more CPU on 1000 programs'
    pieces than on the copying.
    """
    held: list[bytes] = []
    held_bytes = 0
    for chunk in chunks:
        held.append(chunk)
        held_bytes += len(chunk)
        if held_bytes >= size:
            yield b"".join(held)
            held, held_bytes = [], 0
    if held:
        yield b"".join(held)


def clamp(moment: datetime | float | None) -> datetime:
    """A ZIP-storable time: aware, not before 1980; now when unknown."""
    if moment is None:
        moment = datetime.now(UTC)
    elif isinstance(moment, int | float):
        moment = datetime.fromtimestamp(moment, UTC)
    elif moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return max(moment, _ZIP_EPOCH)


def _times(modified: datetime) -> tuple[int, int, bytes]:
    """DOS time, DOS date (4.4.6, in UTC) and the "UT" extra field when it can hold the time."""
    moment = min(clamp(modified).astimezone(UTC), _DOS_END)
    dos_time = moment.hour << 11 | moment.minute << 5 | moment.second // 2
    dos_date = (moment.year - 1980) << 9 | moment.month << 5 | moment.day
    seconds = int(moment.timestamp())
    unix_time = struct.pack("<HHBl", 0x5455, 5, 1, seconds) if seconds < 2**31 else b""
    return dos_time, dos_date, unix_time
