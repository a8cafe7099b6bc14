"""Backup assembly: a streaming ZIP writer (stream-zip) with dncq's conventions.

Members stream in with bounded memory; ZIP64 is used per member when its size needs
it (and for the central directory past 65,535 entries). The first member is always
a directory entry, which is never ZIP64 (macOS Archive Utility mishandles a ZIP whose
first member is). Dates before 1980 cannot be stored in a ZIP and are clamped.
Names are flagged UTF-8 by the library.
"""

from __future__ import annotations

import stat
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime

from stream_zip import ZIP_AUTO, Method, stream_zip

_ZIP_EPOCH = datetime(1980, 1, 1, tzinfo=UTC)
_FILE_MODE = stat.S_IFREG | 0o644
_DIR_MODE = stat.S_IFDIR | 0o755


@dataclass(frozen=True)
class Member:
    """One entry: a folder (name ending in /) or a file with its size and bytes."""

    name: str
    modified: datetime
    size: int = 0
    chunks: Iterable[bytes] = ()

    @property
    def is_dir(self) -> bool:
        return self.name.endswith("/")


def clamp(moment: datetime | float | None) -> datetime:
    """A ZIP-storable time: aware, not before 1980; now when unknown."""
    if moment is None:
        moment = datetime.now(UTC)
    elif isinstance(moment, int | float):
        moment = datetime.fromtimestamp(moment, UTC)
    elif moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return max(moment, _ZIP_EPOCH)


def zip_stream(members: Iterable[Member], *, level: int) -> Iterator[bytes]:
    """The ZIP of `members`, as chunks, assembled as they come."""

    def entries() -> Iterator[tuple[str, datetime, int, Method, Iterable[bytes]]]:
        for m in members:
            if m.is_dir:
                # ZIP_AUTO(0) is ZIP_32 at offset 0 (the first member) but may go ZIP64 later:
                # a plain ZIP_32 folder past 4 GiB or 65,535 entries raises or breaks the index.
                yield m.name, clamp(m.modified), _DIR_MODE, ZIP_AUTO(0, level=level), ()
            else:
                yield m.name, clamp(m.modified), _FILE_MODE, ZIP_AUTO(m.size, level=level), m.chunks

    return iter(stream_zip(
        entries(),
        get_compressobj=lambda: zlib.compressobj(wbits=-zlib.MAX_WBITS, level=level),
    ))
