"""Programs kept for drip-feed runs: content-addressed files under the data folder.

A program is stored once by its SHA-256 (`programs/<hex>`), beside a small record of its
size and line count (`<hex>.json`), and is read back a line at a time: a run of a 2 GB
program never holds it. In the distributed mode the data folder is shared between the
API's host and the workers', as the stored backups are.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import AsyncIterator, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import BinaryIO

from jobs.errors import ContractError, ErrorCode
from jobs.folders import private_dir, private_opener
from jobs.settings import Settings

_PROGRAM_ID = re.compile(r"[0-9a-f]{64}")
READ_BYTES = 256 * 1024


@dataclass(frozen=True)
class ProgramInfo:
    """What dncq knows of a stored program."""

    id: str  # SHA-256, hex
    size: int  # bytes
    lines: int  # lines in the file (a last line without its newline counts)


def program_dir(settings: Settings) -> Path:
    """Where stored programs live."""
    return settings.data_dir / "programs"


class _Intake:
    """A program arriving in chunks: written to a temporary file, hashed and counted."""

    def __init__(self, folder: Path) -> None:
        self.folder = private_dir(folder)
        self.temp = folder / f".incoming-{os.getpid()}-{id(self):x}"
        self.file: BinaryIO = open(self.temp, "wb", opener=private_opener)  # noqa: SIM115
        self.digest = hashlib.sha256()
        self.size = self.newlines = 0
        self.last = b"\n"  # the last byte seen: an empty file has no lines

    def add(self, chunk: bytes) -> None:
        if not chunk:
            return
        self.file.write(chunk)
        self.digest.update(chunk)
        self.size += len(chunk)
        self.newlines += chunk.count(b"\n")
        self.last = chunk[-1:]

    def keep(self) -> ProgramInfo:
        """Move the file under its digest; the same program stored twice is kept once."""
        self.file.close()
        info = ProgramInfo(id=self.digest.hexdigest(), size=self.size,
                           lines=self.newlines + (self.last != b"\n"))
        final = self.folder / info.id
        os.replace(self.temp, final)  # the same bytes under the same name: replacing is harmless
        meta = self.folder / f"{info.id}.json"
        temp_meta = meta.with_name(f".{meta.name}.{os.getpid()}")
        with open(temp_meta, "w", opener=private_opener) as out:
            json.dump(asdict(info), out)
        os.replace(temp_meta, meta)
        return info

    def discard(self) -> None:
        self.file.close()
        self.temp.unlink(missing_ok=True)


def store(settings: Settings, chunks: Iterator[bytes]) -> ProgramInfo:
    """Keep a program given as chunks; nothing is left behind if reading them fails."""
    intake = _Intake(program_dir(settings))
    try:
        for chunk in chunks:
            intake.add(chunk)
        return intake.keep()
    except BaseException:
        intake.discard()
        raise


async def store_stream(settings: Settings, chunks: AsyncIterator[bytes]) -> ProgramInfo:
    """`store` for a request body arriving asynchronously."""
    intake = _Intake(program_dir(settings))
    try:
        async for chunk in chunks:
            intake.add(chunk)
        return intake.keep()
    except BaseException:
        intake.discard()
        raise


def info(settings: Settings, program_id: str) -> ProgramInfo:
    """The stored program's record; 158 when there is no such program."""
    path = _path(settings, program_id)
    try:
        record = json.loads(path.with_name(f"{path.name}.json").read_text())
    except FileNotFoundError:
        raise ContractError(ErrorCode.PATH_NOT_FOUND, f"no stored program {program_id}") from None
    return ProgramInfo(**record)


def lines(settings: Settings, program_id: str, *, start_line: int = 1) -> Iterator[bytes]:
    """The program's lines from `start_line` (1-based), without their line endings."""
    path = _path(settings, program_id)
    with open(path, "rb", buffering=READ_BYTES) as source:
        for number, line in enumerate(source, start=1):
            if number >= start_line:
                yield line.rstrip(b"\r\n")


def text_lines(settings: Settings, program_id: str) -> Iterator[str]:
    """The program's lines as text (Latin-1: every byte is a character, none is refused)."""
    for line in lines(settings, program_id):
        yield line.decode("latin-1")


def _path(settings: Settings, program_id: str) -> Path:
    if not _PROGRAM_ID.fullmatch(program_id or ""):
        raise ContractError(ErrorCode.BAD_PARAMETER,
                            "a program id is the SHA-256 of the program, 64 hex digits")
    return program_dir(settings) / program_id
