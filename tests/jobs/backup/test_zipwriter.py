"""The writer of pre-deflated members: archives that zipfile and Info-ZIP `unzip -t` accept."""

from __future__ import annotations

import calendar
import os
import random
import shutil
import struct
import time
import tracemalloc
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest

from jobs.backup.zipwriter import DEFLATED, STORED, PreparedMember, clamp, deflated, write_zip
from tests.jobs.backup.zip_checks import (
    BIG_FREE_BYTES,
    BIG_SIZE,
    UNIX_TIME_EXTRA,
    UTF8_FLAG,
    WHEN,
    ZIP64_EXTRA,
    MiB,
    extras,
    local_header,
    sample_contents,
    unzip_test,
)


def write(path: Path, members: Iterable[PreparedMember]) -> Path:
    """Stream the ZIP of `members` to `path`, chunk by chunk."""
    with open(path, "wb") as f:
        for chunk in write_zip(members):
            f.write(chunk)
    return path


def stored(name: str, data: bytes) -> PreparedMember:
    return PreparedMember(name, WHEN, zlib.crc32(data), len(data), len(data), STORED, [data])


def split(member: PreparedMember, step: int = 1000) -> PreparedMember:
    """The same member with its bytes in uneven chunks, so the writer has to pass them on."""
    body = b"".join(member.chunks)
    return PreparedMember(member.name, member.modified, member.crc32, member.compressed_size,
                          member.size, member.method,
                          [body[i:i + step] for i in range(0, len(body), step)])


@pytest.fixture
def contents() -> dict[str, bytes]:
    return sample_contents()


@pytest.fixture
def small_zip(tmp_path: Path, contents: dict[str, bytes]) -> Path:
    members = [PreparedMember("backup/", WHEN)]
    for n, (name, data) in enumerate(contents.items()):
        members.append(split(stored(name, data) if n % 2 else
                             deflated(name, WHEN, data, level=6)))
    return write(tmp_path / "small.zip", members)


def test_small_archive_opens_with_zipfile_and_contents_are_byte_identical(
        small_zip: Path, contents: dict[str, bytes]) -> None:
    with zipfile.ZipFile(small_zip) as z:
        assert z.testzip() is None
        assert z.namelist() == ["backup/", *contents]
        assert [i.compress_type for i in z.infolist()[1:]] == [DEFLATED, STORED] * 2
        for name, data in contents.items():
            assert z.read(name) == data


def test_small_archive_passes_unzip_test(small_zip: Path) -> None:
    unzip_test(small_zip)


def test_first_member_is_a_directory_entry_without_zip64(small_zip: Path) -> None:
    with zipfile.ZipFile(small_zip) as z:
        first = z.infolist()[0]
    assert first.is_dir() and first.filename == "backup/" and first.header_offset == 0
    assert ZIP64_EXTRA not in extras(first.extra)
    version, local_extras = local_header(small_zip, 0)
    assert version == 20 and ZIP64_EXTRA not in local_extras


def test_local_headers_carry_the_sizes_without_a_data_descriptor(small_zip: Path) -> None:
    with zipfile.ZipFile(small_zip) as z:
        infos = z.infolist()
    with open(small_zip, "rb") as f:
        for info in infos:
            f.seek(info.header_offset)
            fields = struct.unpack("<IHHHHHIIIHH", f.read(30))
            flags, crc, compressed, size = fields[2], fields[6], fields[7], fields[8]
            assert not flags & 0x0008  # bit 3: sizes in a data descriptor after the data
            assert (crc, compressed, size) == (info.CRC, info.compress_size, info.file_size)


def test_a_member_whose_bytes_differ_from_its_announced_size_is_refused(
        tmp_path: Path) -> None:
    short = PreparedMember("a.nc", WHEN, zlib.crc32(b"M30"), 4, 3, STORED, [b"M30"])
    with pytest.raises(ValueError, match="3 bytes, 4 announced"):
        write(tmp_path / "bad.zip", [PreparedMember("a/", WHEN), short])


def test_dates_before_1980_are_stored_as_1980_01_01(tmp_path: Path) -> None:
    old = datetime(1970, 1, 1, tzinfo=UTC)
    path = write(tmp_path / "old.zip", [PreparedMember("old/", old),
                                        deflated("old/a.nc", old, b"M30", level=6)])
    with zipfile.ZipFile(path) as z:
        assert [i.date_time for i in z.infolist()] == [(1980, 1, 1, 0, 0, 0)] * 2
        assert z.read("old/a.nc") == b"M30"


def test_utf8_names_round_trip_with_the_utf8_flag(tmp_path: Path) -> None:
    path = write(tmp_path / "utf8.zip", [
        PreparedMember("ünï/", WHEN), deflated("ünï/cødé.nc", WHEN, b"G0\n%", level=6)])
    with zipfile.ZipFile(path) as z:
        assert z.namelist() == ["ünï/", "ünï/cødé.nc"]
        assert all(i.flag_bits & UTF8_FLAG for i in z.infolist())
        assert z.read("ünï/cødé.nc") == b"G0\n%"
    unzip_test(path)


MANY_FILES = 65_600  # past the 65,535 entries a ZIP32 central directory can count


@pytest.fixture(scope="module")
def many_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    def members() -> Iterator[PreparedMember]:
        yield PreparedMember("many/", WHEN)
        for i in range(MANY_FILES):
            yield deflated(f"many/{i // 1000:02d}/O{i}.nc", WHEN, f"O{i}\n".encode(), level=6)

    return write(tmp_path_factory.mktemp("many") / "many.zip", members())


@pytest.mark.slow
def test_more_than_65535_entries_open_with_zipfile(many_zip: Path) -> None:
    with zipfile.ZipFile(many_zip) as z:
        assert len(z.namelist()) == MANY_FILES + 1
        last = MANY_FILES - 1
        assert z.read(f"many/{last // 1000:02d}/O{last}.nc") == f"O{last}\n".encode()


@pytest.mark.slow
def test_more_than_65535_entries_pass_unzip_test(many_zip: Path) -> None:
    unzip_test(many_zip)


@pytest.mark.slow
def test_folders_past_entry_65535_still_get_a_zip64_central_directory(tmp_path: Path) -> None:
    def members() -> Iterator[PreparedMember]:
        yield PreparedMember("top/", WHEN)
        for i in range(65_534):
            yield stored(f"top/{i}", b"x")
        for i in range(100):
            yield PreparedMember(f"top/d{i}/", WHEN)

    path = write(tmp_path / "folders.zip", members())
    with zipfile.ZipFile(path) as z:
        assert len(z.namelist()) == 65_635
    unzip_test(path)


BIG_TIMEOUT_S = 1200  # the first test to use big_zip also writes it (~5 GB) on a loaded host


def repeated(pattern: bytes) -> Iterator[bytes]:
    for _ in range(BIG_SIZE // len(pattern)):
        yield pattern


@pytest.fixture(scope="module")
def gcode_pattern() -> bytes:
    # 512 lines (~9 KiB) repeated: within deflate's 32 KiB window, so level 1 runs fast.
    rng = random.Random(3)
    lines = b"".join(f"G1 X{rng.randint(0, 999)}.{rng.randint(0, 9)} "
                     f"Y{rng.randint(0, 99)}.5\n".encode() for _ in range(512))
    return (lines * (MiB // len(lines) + 1))[:MiB]


@pytest.fixture(scope="module")
def random_pattern() -> bytes:
    return random.Random(4).randbytes(MiB)


def deflate_to(spool: Path, name: str, chunks: Iterable[bytes]) -> PreparedMember:
    """Deflate `chunks` at level 1 into `spool`, as a backup worker does while fetching."""
    deflater = zlib.compressobj(1, zlib.DEFLATED, -zlib.MAX_WBITS)
    crc = size = 0
    with open(spool, "wb") as out:
        for chunk in chunks:
            crc, size = zlib.crc32(chunk, crc), size + len(chunk)
            out.write(deflater.compress(chunk))
        out.write(deflater.flush())

    def body() -> Iterator[bytes]:
        with open(spool, "rb") as f:
            while chunk := f.read(MiB):
                yield chunk

    return PreparedMember(name, WHEN, crc, spool.stat().st_size, size, DEFLATED, body())


@pytest.fixture(scope="module")
def big_zip(tmp_path_factory: pytest.TempPathFactory, random_pattern: bytes,
            gcode_pattern: bytes) -> Iterator[Path]:
    folder = tmp_path_factory.mktemp("big")
    free = shutil.disk_usage(folder).free
    if free < BIG_FREE_BYTES:
        pytest.skip(f"the >4 GiB archive needs {BIG_FREE_BYTES / 1e9:.0f} GB free in "
                    f"{folder}, only {free / 1e9:.1f} GB are")
    huge_nc = deflate_to(folder / "huge.nc.deflate", "big/huge.nc", repeated(gcode_pattern))
    crc = 0
    for chunk in repeated(random_pattern):
        crc = zlib.crc32(chunk, crc)
    path = write(folder / "big.zip", [
        PreparedMember("big/", WHEN),
        huge_nc,  # over 4 GiB plain, well under deflated
        # Stored: past 4 GiB in the archive too, without deflating 4 GiB a second time.
        PreparedMember("big/huge.bin", WHEN, crc, BIG_SIZE, BIG_SIZE, STORED,
                       repeated(random_pattern)),
        PreparedMember("big/after/", WHEN),  # starts past the 4 GiB offset
        deflated("big/after/O1.nc", WHEN, b"M30", level=6),
    ])
    (folder / "huge.nc.deflate").unlink()
    yield path
    path.unlink()  # pytest keeps the last three temp folders; don't keep 4.5 GB in each


def read_back(archive: zipfile.ZipFile, name: str, pattern: bytes) -> int:
    """Bytes read from the member, each block checked; zipfile checks the CRC at the end."""
    read = 0
    with archive.open(name) as f:
        while chunk := f.read(len(pattern)):
            assert chunk == pattern
            read += len(chunk)
    return read


@pytest.mark.slow
@pytest.mark.timeout(BIG_TIMEOUT_S)
def test_members_over_4_gib_stream_back_with_their_size_and_crc(
        big_zip: Path, gcode_pattern: bytes, random_pattern: bytes) -> None:
    with zipfile.ZipFile(big_zip) as z:
        assert z.getinfo("big/huge.nc").file_size == BIG_SIZE
        assert z.getinfo("big/huge.bin").compress_size == BIG_SIZE
        assert read_back(z, "big/huge.nc", gcode_pattern) == BIG_SIZE
        assert read_back(z, "big/huge.bin", random_pattern) == BIG_SIZE
    version, local_extras = local_header(big_zip, 0)
    assert version == 20 and ZIP64_EXTRA not in local_extras


@pytest.mark.slow
@pytest.mark.timeout(BIG_TIMEOUT_S)
def test_folders_and_files_after_4_gib_are_readable(big_zip: Path) -> None:
    with zipfile.ZipFile(big_zip) as z:
        assert z.getinfo("big/after/").header_offset > 0xFFFFFFFF
        assert z.getinfo("big/after/").is_dir()
        assert z.getinfo("big/after/O1.nc").header_offset > 0xFFFFFFFF
        assert z.read("big/after/O1.nc") == b"M30"


@pytest.mark.slow
@pytest.mark.timeout(BIG_TIMEOUT_S)
def test_members_over_4_gib_pass_unzip_test(big_zip: Path) -> None:
    unzip_test(big_zip)


def test_clamp_moves_dates_before_1980_to_1980_01_01_utc() -> None:
    epoch = datetime(1980, 1, 1, tzinfo=UTC)
    assert clamp(datetime(1975, 6, 1, 12, 0, tzinfo=UTC)) == epoch
    assert clamp(datetime(1969, 12, 31)) == epoch
    assert clamp(0.0) == epoch
    assert clamp(WHEN) == WHEN


def test_clamp_treats_naive_datetimes_as_utc() -> None:
    assert clamp(datetime(2024, 5, 6, 7, 8, 10)) == WHEN


def test_naive_modified_time_is_stored_as_utc_whatever_the_local_zone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A naive datetime's .timestamp() would use the local zone; make that zone not UTC.
    monkeypatch.setenv("TZ", "America/New_York")
    time.tzset()
    naive = datetime(2024, 5, 6, 7, 8, 10)
    try:
        path = write(tmp_path / "naive.zip", [
            PreparedMember("n/", naive),
            PreparedMember("n/a.nc", naive, zlib.crc32(b"M30"), 3, 3, STORED, [b"M30"])])
    finally:
        monkeypatch.undo()
        time.tzset()
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("n/a.nc")
    assert info.date_time == (2024, 5, 6, 7, 8, 10)
    flags, seconds = struct.unpack("<Bl", extras(info.extra)[UNIX_TIME_EXTRA][:5])
    assert flags & 1 and seconds == calendar.timegm(WHEN.timetuple())


def test_memory_stays_flat_while_writing_200_mb() -> None:
    block = random.Random(2).randbytes(MiB)  # stored: output is as big as input
    crc = 0
    for _ in range(10):
        crc = zlib.crc32(block, crc)

    def members() -> Iterator[PreparedMember]:
        yield PreparedMember("flat/", WHEN)
        for i in range(20):
            yield PreparedMember(f"flat/{i}.bin", WHEN, crc, 10 * MiB, 10 * MiB, STORED,
                                 (block for _ in range(10)))

    tracemalloc.start()
    try:
        written = 0
        with open(os.devnull, "wb") as f:
            for chunk in write_zip(members()):
                written += f.write(chunk)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert written > 200 * MiB
    assert peak < 30 * MiB, f"peak {peak / MiB:.1f} MiB while writing {written / MiB:.0f} MiB"
