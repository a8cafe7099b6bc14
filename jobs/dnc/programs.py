"""Programs kept for drip-feed runs: content-addressed blobs with a small line-count record.

A program's bytes are a blob of the library's store (jobs.library.blobs), so a library
version runs without a copy; beside it, `programs/<hex>.json` records its size and line
count. Programs are read back a line at a time: a run of a 2 GB program never holds it. In
the distributed mode the data folder is shared between the API's host and the workers', as
the stored backups are.
"""

from __future__ import annotations

import json
import os
from collections.abc import AsyncIterator, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

from jobs.errors import ContractError, ErrorCode
from jobs.folders import private_dir, private_opener
from jobs.library import blobs
from jobs.settings import Settings

READ_BYTES = blobs.READ_BYTES


@dataclass(frozen=True)
class ProgramInfo:
    """What dncq knows of a stored program."""

    id: str  # SHA-256, hex
    size: int  # bytes
    lines: int  # lines in the file (a last line without its newline counts)


def program_dir(settings: Settings) -> Path:
    """Where the programs' line-count records live."""
    return settings.data_dir / "programs"


class _Counter:
    """Counts lines of chunks as they pass into the blob store."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.intake = blobs.Intake(settings)
        self.newlines = 0
        self.last = b"\n"  # the last byte seen: an empty file has no lines

    def add(self, chunk: bytes) -> None:
        if not chunk:
            return
        self.intake.add(chunk)
        self.newlines += chunk.count(b"\n")
        self.last = chunk[-1:]

    def keep(self) -> ProgramInfo:
        blob = self.intake.keep()
        info = ProgramInfo(id=blob.sha256, size=blob.size,
                           lines=self.newlines + (self.last != b"\n"))
        _write_record(self.settings, info)
        return info


def _write_record(settings: Settings, info: ProgramInfo) -> None:
    meta = private_dir(program_dir(settings)) / f"{info.id}.json"
    temp_meta = meta.with_name(f".{meta.name}.{os.getpid()}-{id(info):x}")
    with open(temp_meta, "w", opener=private_opener) as out:
        json.dump(asdict(info), out)
    os.replace(temp_meta, meta)


def store(settings: Settings, chunks: Iterator[bytes]) -> ProgramInfo:
    """Keep a program given as chunks; nothing is left behind if reading them fails."""
    counter = _Counter(settings)
    try:
        for chunk in chunks:
            counter.add(chunk)
        return counter.keep()
    except BaseException:
        counter.intake.discard()
        raise


async def store_stream(settings: Settings, chunks: AsyncIterator[bytes]) -> ProgramInfo:
    """`store` for a request body arriving asynchronously."""
    counter = _Counter(settings)
    try:
        async for chunk in chunks:
            counter.add(chunk)
        return counter.keep()
    except BaseException:
        counter.intake.discard()
        raise


def info(settings: Settings, program_id: str) -> ProgramInfo:
    """The stored program's record; 158 when there is no such program.

    Content stored by the library has no record yet: it is counted (streamed) once and
    recorded, so a library version is run from its blob as it is.
    """
    blob = blobs.path(settings, program_id)
    try:
        record = json.loads((program_dir(settings) / f"{program_id}.json").read_text())
    except FileNotFoundError:
        if not blob.is_file():
            raise ContractError(ErrorCode.PATH_NOT_FOUND,
                                f"no stored program {program_id}") from None
        return _count(settings, program_id)
    return ProgramInfo(**record)


def _count(settings: Settings, program_id: str) -> ProgramInfo:
    size = newlines = 0
    last = b"\n"
    for chunk in blobs.read(settings, program_id):
        size += len(chunk)
        newlines += chunk.count(b"\n")
        last = chunk[-1:]
    counted = ProgramInfo(id=program_id, size=size, lines=newlines + (last != b"\n"))
    _write_record(settings, counted)
    return counted


def lines(settings: Settings, program_id: str, *, start_line: int = 1) -> Iterator[bytes]:
    """The program's lines from `start_line` (1-based), without their line endings."""
    with blobs.open_blob(settings, program_id) as source:
        for number, line in enumerate(source, start=1):
            if number >= start_line:
                yield line.rstrip(b"\r\n")


def text_lines(settings: Settings, program_id: str) -> Iterator[str]:
    """The program's lines as text (Latin-1: every byte is a character, none is refused)."""
    for line in lines(settings, program_id):
        yield line.decode("latin-1")
