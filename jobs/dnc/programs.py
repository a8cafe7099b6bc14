"""Programs kept for drip-feed runs: content-addressed blobs with a small line-count record.

A program's bytes are a blob of the library's store (jobs.library.blobs), so a library
version runs without a copy; beside it, `programs/<hex>.json` records its size and line
count. Programs are read back a line at a time: a run of a 2 GB program never holds it. A
line ends with CR LF, LF, CR or LF CR alike, as controls and their editors write them. In
the distributed mode the data folder is shared between the API's host and the workers', as
the stored backups are.
"""

from __future__ import annotations

import json
import os
from collections.abc import AsyncIterator, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from jobs.errors import ContractError, ErrorCode
from jobs.folders import private_dir, private_opener
from jobs.library import blobs
from jobs.library.line_ends import LineEnds, split_lines
from jobs.settings import Settings
from worker.transports.dnc_wire import MAX_LINE_BYTES  # the longest line a run sends

READ_BYTES = blobs.READ_BYTES
COUNTING = 2  # how records count lines: one of an earlier counting is counted again


@dataclass(frozen=True)
class ProgramInfo:
    """What dncq knows of a stored program."""

    id: str  # SHA-256, hex
    size: int  # bytes
    lines: int  # lines in the file (a last line without its newline counts)
    longest_line: int = 0  # bytes, its line ending left out
    longest_line_at: int = 0  # its line number (1-based; 0 in an empty file)

    def view(self) -> dict[str, Any]:
        """What the API says of it."""
        return {"id": self.id, "size": self.size, "lines": self.lines}

    def refusal(self) -> str | None:
        """Why no control can be drip-fed this program, found before the run starts (an
        empty program held a dnc control waiting for ever; a line over the link's frame was
        found only after the control had been told to expect the run)."""
        if not self.size:
            return "the program is empty"
        if self.longest_line > MAX_LINE_BYTES:
            return (f"line {self.longest_line_at} is {self.longest_line:,} bytes long, more "
                    f"than the {MAX_LINE_BYTES:,} a run sends as one line")
        return None


def program_dir(settings: Settings) -> Path:
    """Where the programs' line-count records live."""
    return settings.data_dir / "programs"


class _Shape:
    """A program's size, lines and longest line, counted as its chunks pass (in C: the lines
    of a 2 GB program are split and measured, never looped over)."""

    def __init__(self) -> None:
        self.size = self.newlines = self.longest = self.longest_at = 0
        self.current = 0  # bytes of the line not yet ended
        self.last = b"\n"  # the last byte seen, line ends made LF: an empty file has no lines
        self.ends = LineEnds()

    def add(self, chunk: bytes) -> None:
        self.size += len(chunk)
        self._measure(self.ends.add(chunk))

    def _measure(self, text: bytes) -> None:
        if not text:
            return
        parts = text.split(b"\n")  # the first continues the line in progress
        lengths = list(map(len, parts))
        lengths[0] += self.current
        ended = lengths[:-1]  # the last part goes on in the next chunk
        if ended and (longest := max(ended)) > self.longest:
            at = ended.index(longest)
            self.longest = longest
            self.longest_at = self.newlines + at + 1
        self.current = lengths[-1]
        self.newlines += len(ended)
        self.last = text[-1:]

    def info(self, program_id: str) -> ProgramInfo:
        self._measure(self.ends.end())
        longest, longest_at = self.longest, self.longest_at
        if self.current > longest:  # a last line without its newline
            longest, longest_at = self.current, self.newlines + 1
        return ProgramInfo(id=program_id, size=self.size,
                           lines=self.newlines + (self.last != b"\n"), longest_line=longest,
                           longest_line_at=longest_at)


class _Counter:
    """Counts lines of chunks as they pass into the blob store."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.intake = blobs.Intake(settings)
        self.shape = _Shape()

    def add(self, chunk: bytes) -> None:
        self.intake.add(chunk)
        self.shape.add(chunk)

    def keep(self) -> ProgramInfo:
        blob = self.intake.keep()
        info = self.shape.info(blob.sha256)
        _write_record(self.settings, info)
        return info


def _write_record(settings: Settings, info: ProgramInfo) -> None:
    meta = private_dir(program_dir(settings)) / f"{info.id}.json"
    temp_meta = meta.with_name(f".{meta.name}.{os.getpid()}-{id(info):x}")
    with open(temp_meta, "w", opener=private_opener) as out:
        json.dump({**asdict(info), "counting": COUNTING}, out)
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
    if record.pop("counting", 1) != COUNTING:  # lines measured, or CR ends counted, since
        return _count(settings, program_id)
    return ProgramInfo(**record)


def _count(settings: Settings, program_id: str) -> ProgramInfo:
    shape = _Shape()
    for chunk in blobs.read(settings, program_id):
        shape.add(chunk)
    counted = shape.info(program_id)
    _write_record(settings, counted)
    return counted


def lines(settings: Settings, program_id: str, *, start_line: int = 1) -> Iterator[bytes]:
    """The program's lines from `start_line` (1-based), without their line endings."""
    for number, line in enumerate(split_lines(blobs.read(settings, program_id)), start=1):
        if number >= start_line:
            yield line


def text_lines(settings: Settings, program_id: str) -> Iterator[str]:
    """The program's lines as text (Latin-1: every byte is a character, none is refused)."""
    for line in lines(settings, program_id):
        yield line.decode("latin-1")
