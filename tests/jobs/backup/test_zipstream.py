"""The streaming ZIP writer: archives that zipfile and Info-ZIP `unzip -t` accept, at any size."""

from __future__ import annotations

import calendar
import os
import random
import shutil
import struct
import time
import tracemalloc
import zipfile
from collections.abc import Iterable, Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest

from jobs.backup.zipstream import Member, clamp, zip_stream
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


def write_zip(path: Path, members: Iterable[Member], *, level: int = 6) -> Path:
    """Stream the ZIP of `members` to `path`, chunk by chunk."""
    with open(path, "wb") as f:
        for chunk in zip_stream(members, level=level):
            f.write(chunk)
    return path


def small_members(contents: dict[str, bytes]) -> Iterator[Member]:
    yield Member("backup/", WHEN)
    for name, data in contents.items():
        # Split in uneven chunks so the writer has to join them.
        chunks = [data[i:i + 1000] for i in range(0, len(data), 1000)]
        yield Member(name, WHEN, len(data), chunks)


@pytest.fixture
def contents() -> dict[str, bytes]:
    return sample_contents()


@pytest.fixture
def small_zip(tmp_path: Path, contents: dict[str, bytes]) -> Path:
    return write_zip(tmp_path / "small.zip", small_members(contents))


def test_small_archive_opens_with_zipfile_and_contents_are_byte_identical(
        small_zip: Path, contents: dict[str, bytes]) -> None:
    with zipfile.ZipFile(small_zip) as z:
        assert z.testzip() is None
        assert z.namelist() == ["backup/", *contents]
        for name, data in contents.items():
            assert z.read(name) == data


def test_small_archive_passes_unzip_test(small_zip: Path) -> None:
    unzip_test(small_zip)


def test_first_member_is_a_directory_entry_without_zip64(small_zip: Path) -> None:
    with zipfile.ZipFile(small_zip) as z:
        first = z.infolist()[0]
    assert first.is_dir() and first.filename == "backup/"
    assert first.header_offset == 0
    assert ZIP64_EXTRA not in extras(first.extra)
    version, local_extras = local_header(small_zip, 0)
    assert version == 20 and ZIP64_EXTRA not in local_extras


def test_clamp_moves_dates_before_1980_to_1980_01_01_utc() -> None:
    epoch = datetime(1980, 1, 1, tzinfo=UTC)
    assert clamp(datetime(1975, 6, 1, 12, 0, tzinfo=UTC)) == epoch
    assert clamp(datetime(1969, 12, 31)) == epoch
    assert clamp(0.0) == epoch
    assert clamp(WHEN) == WHEN


def test_dates_before_1980_are_stored_as_1980_01_01(tmp_path: Path) -> None:
    old = datetime(1970, 1, 1, tzinfo=UTC)
    path = write_zip(tmp_path / "old.zip", [Member("old/", old),
                                            Member("old/a.nc", old, 3, [b"M30"])])
    with zipfile.ZipFile(path) as z:
        assert [i.date_time for i in z.infolist()] == [(1980, 1, 1, 0, 0, 0)] * 2
        assert z.read("old/a.nc") == b"M30"


def test_clamp_treats_naive_datetimes_as_utc() -> None:
    assert clamp(datetime(2024, 5, 6, 7, 8, 10)) == WHEN


def test_naive_modified_time_is_stored_as_utc_whatever_the_local_zone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A naive datetime's .timestamp() would use the local zone; make that zone not UTC.
    monkeypatch.setenv("TZ", "America/New_York")
    time.tzset()
    try:
        path = write_zip(tmp_path / "naive.zip", [
            Member("n/", datetime(2024, 5, 6, 7, 8, 10)),
            Member("n/a.nc", datetime(2024, 5, 6, 7, 8, 10), 3, [b"M30"])])
    finally:
        monkeypatch.undo()
        time.tzset()
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("n/a.nc")
    assert info.date_time == (2024, 5, 6, 7, 8, 10)
    flags, seconds = struct.unpack("<Bl", extras(info.extra)[UNIX_TIME_EXTRA][:5])
    assert flags & 1 and seconds == calendar.timegm(WHEN.timetuple())


def test_utf8_names_round_trip_with_the_utf8_flag(tmp_path: Path) -> None:
    path = write_zip(tmp_path / "utf8.zip", [
        Member("ünï/", WHEN), Member("ünï/cødé.nc", WHEN, 4, [b"G0\n%"])])
    with zipfile.ZipFile(path) as z:
        assert z.namelist() == ["ünï/", "ünï/cødé.nc"]
        assert all(i.flag_bits & UTF8_FLAG for i in z.infolist())
        assert z.read("ünï/cødé.nc") == b"G0\n%"
    unzip_test(path)


MANY_FILES = 65_600  # past the 65,535 entries a ZIP32 central directory can count


def many_members() -> Iterator[Member]:
    yield Member("many/", WHEN)
    for i in range(MANY_FILES):
        data = f"O{i}\n".encode()
        yield Member(f"many/{i // 1000:02d}/O{i}.nc", WHEN, len(data), [data])


@pytest.fixture(scope="module")
def many_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_zip(tmp_path_factory.mktemp("many") / "many.zip", many_members())


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
    # Only folders come after entry 65,535, so they must be the ones to upgrade the index.
    def members() -> Iterator[Member]:
        yield Member("top/", WHEN)
        for i in range(65_534):
            yield Member(f"top/{i}", WHEN, 1, [b"x"])
        for i in range(100):
            yield Member(f"top/d{i}/", WHEN)

    path = write_zip(tmp_path / "folders.zip", members())
    with zipfile.ZipFile(path) as z:
        assert len(z.namelist()) == 65_635
    unzip_test(path)


def big_chunks(pattern: bytes) -> Iterator[bytes]:
    for _ in range(BIG_SIZE // len(pattern)):
        yield pattern


@pytest.fixture(scope="module")
def pattern() -> bytes:
    return random.Random(4).randbytes(MiB)


@pytest.fixture(scope="module")
def big_zip(tmp_path_factory: pytest.TempPathFactory, pattern: bytes) -> Iterator[Path]:
    folder = tmp_path_factory.mktemp("big")
    free = shutil.disk_usage(folder).free
    if free < BIG_FREE_BYTES:
        pytest.skip(f"the >4 GiB archive needs {BIG_FREE_BYTES / 1e9:.0f} GB free in "
                    f"{folder}, only {free / 1e9:.1f} GB are")
    # Level 0 (stored deflate blocks) keeps the archive past 4 GiB and is the fastest to write.
    path = write_zip(folder / "big.zip", [
        Member("big/", WHEN),
        Member("big/huge.bin", WHEN, BIG_SIZE, big_chunks(pattern)),
        Member("big/after/", WHEN),  # starts past the 4 GiB offset
        Member("big/after/O1.nc", WHEN, 3, [b"M30"]),
    ], level=0)
    yield path
    path.unlink()  # pytest keeps the last three temp folders; don't keep 4.5 GB in each


@pytest.mark.slow
def test_member_over_4_gib_streams_back_with_its_size_and_crc(
        big_zip: Path, pattern: bytes) -> None:
    with zipfile.ZipFile(big_zip) as z:
        assert z.getinfo("big/huge.bin").file_size == BIG_SIZE
        read = 0
        # Reading to the end makes zipfile check the CRC (BadZipFile on a mismatch).
        with z.open("big/huge.bin") as f:
            while chunk := f.read(len(pattern)):
                assert chunk == pattern
                read += len(chunk)
    assert read == BIG_SIZE


@pytest.mark.slow
def test_entries_after_4_gib_are_readable(big_zip: Path) -> None:
    with zipfile.ZipFile(big_zip) as z:
        assert z.getinfo("big/after/").header_offset > 0xFFFFFFFF
        assert z.getinfo("big/after/").is_dir()
        assert z.read("big/after/O1.nc") == b"M30"


@pytest.mark.slow
def test_member_over_4_gib_passes_unzip_test(big_zip: Path) -> None:
    unzip_test(big_zip)


def test_memory_stays_flat_while_streaming_200_mb() -> None:
    block = random.Random(2).randbytes(MiB)  # incompressible: output is as big as input

    def members() -> Iterator[Member]:
        yield Member("flat/", WHEN)
        for i in range(20):
            yield Member(f"flat/{i}.bin", WHEN, 10 * MiB, (block for _ in range(10)))

    tracemalloc.start()
    try:
        written = 0
        with open(os.devnull, "wb") as f:
            for chunk in zip_stream(members(), level=1):
                written += f.write(chunk)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert written > 200 * MiB
    assert peak < 30 * MiB, f"peak {peak / MiB:.1f} MiB while streaming {written / MiB:.0f} MiB"
