"""What the ZIP tests check an archive with: Info-ZIP and the fields of its headers."""

from __future__ import annotations

import random
import shutil
import struct
import subprocess
from datetime import UTC, datetime
from pathlib import Path

from tests.servers import unavailable

WHEN = datetime(2024, 5, 6, 7, 8, 10, tzinfo=UTC)
MiB = 1024 * 1024
ZIP64_EXTRA = 0x0001  # the ZIP64 extended information extra field
UNIX_TIME_EXTRA = 0x5455  # "UT": the extended timestamp extra field
UTF8_FLAG = 0x0800  # bit 11 of the general purpose flags: the name is UTF-8
BIG_SIZE = 4300 * MiB  # ~4.2 GiB: past the 4 GiB ZIP32 limit
BIG_FREE_BYTES = 10 * 10**9  # the >4 GiB archive is ~4.5 GB on disk; keep room to spare


def unzip_test(path: Path) -> None:
    """Assert that Info-ZIP's `unzip -t` finds no errors in the archive."""
    unzip = shutil.which("unzip")
    if unzip is None:
        unavailable("unzip is not installed (apt-get install unzip)")
        return
    result = subprocess.run([unzip, "-tq", str(path)], capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]


def unzipped(path: Path, into: Path) -> dict[str, bytes]:
    """Unpack the archive with Info-ZIP's `unzip` into `into`; every file written, by its
    path below `into`."""
    unzip = shutil.which("unzip")
    if unzip is None:
        unavailable("unzip is not installed (apt-get install unzip)")
    result = subprocess.run([unzip, "-q", str(path), "-d", str(into)], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    return {p.relative_to(into).as_posix(): p.read_bytes() for p in into.rglob("*")
            if p.is_file()}


def extras(raw: bytes) -> dict[int, bytes]:
    """The extra fields of a ZIP header, by header id."""
    fields: dict[int, bytes] = {}
    while len(raw) >= 4:
        header_id, size = struct.unpack("<HH", raw[:4])
        fields[header_id] = raw[4:4 + size]
        raw = raw[4 + size:]
    return fields


def local_header(path: Path, offset: int) -> tuple[int, dict[int, bytes]]:
    """The version needed to extract and the extra fields of the local header at `offset`."""
    with open(path, "rb") as f:
        f.seek(offset)
        fixed = f.read(30)
        signature, version, *_, name_length, extra_length = struct.unpack("<IHHHHHIIIHH", fixed)
        assert signature == 0x04034B50
        f.seek(name_length, 1)
        return version, extras(f.read(extra_length))


def sample_contents() -> dict[str, bytes]:
    """Files of a small archive: G-code, an empty file, random and repetitive bytes."""
    rng = random.Random(1)
    return {
        "backup/O1000.nc": b"%\nO1000\nG21 G90\nG0 X0 Y0\nM30\n%\n",
        "backup/empty.nc": b"",
        "backup/sub/random.bin": rng.randbytes(200_000),
        "backup/sub/repeat.nc": b"G1 X1.0 Y2.0 F300\n" * 20_000,
    }
