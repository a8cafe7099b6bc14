"""Raw deflate (a ZIP member's bytes) of a backup's files at the configured level.

Levels 1-3 deflate with ISA-L, which on G-code runs 2.3-3.4x as fast as zlib-ng's level 3
into members within 3 % of its size (docs/backups.md#zip-details); 0 stores, and 4-9 are
zlib-ng's levels, for a shop that would rather spend CPU than disk. Both let go of the
interpreter lock while they deflate, so the workers spread it over the cores.
"""

from __future__ import annotations

from typing import Protocol

from isal import isal_zlib
from zlib_ng import zlib_ng

ISAL_LEVELS = range(1, 4)  # ISA-L's own levels; its level 0 is not "stored", so 0 is zlib-ng's


class Deflater(Protocol):
    """A raw deflate stream: `compress` each chunk, then `flush` once."""

    def compress(self, data: bytes, /) -> bytes: ...

    def flush(self) -> bytes: ...


def whole(data: bytes, level: int) -> bytes:
    """The raw deflate of `data`, in one call."""
    if level in ISAL_LEVELS:
        return isal_zlib.compress(data, level, -isal_zlib.MAX_WBITS)
    return zlib_ng.compress(data, level, -zlib_ng.MAX_WBITS)


def stream(level: int) -> Deflater:
    """A raw deflate stream, for a file read in several chunks."""
    if level in ISAL_LEVELS:
        return isal_zlib.compressobj(level, isal_zlib.DEFLATED, -isal_zlib.MAX_WBITS)
    return zlib_ng.compressobj(level, zlib_ng.DEFLATED, -zlib_ng.MAX_WBITS)
