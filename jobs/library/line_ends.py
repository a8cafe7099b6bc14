"""Lines of a program as its bytes pass in chunks: CR LF, LF, CR and LF CR are each one line
end, read from the left, as controls and their editors write them (a CR-only file from an
old control is as many lines as its editor shows). Drip-feed runs count and send lines by
it, and the library's analysis numbers them alike."""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator

LINE_END = re.compile(rb"\r\n|\n\r|\r|\n")  # one line end each, read from the left


class LineEnds:
    """Every line end (LINE_END) made LF as chunks pass: a CR or LF that ends a chunk waits
    for the next one, whose first byte may pair with it."""

    def __init__(self) -> None:
        self.held = b""

    def add(self, chunk: bytes) -> bytes:
        data = self.held + chunk if self.held else chunk
        ends = LINE_END.findall(data[len(data.rstrip(b"\r\n")):])  # those the data ends with
        self.held = ends[-1] if ends and len(ends[-1]) == 1 else b""
        return as_lf(data[:len(data) - len(self.held)])

    def end(self) -> bytes:
        """The line end still held at the end of the data."""
        held, self.held = self.held, b""
        return b"\n" if held else b""


def as_lf(data: bytes) -> bytes:
    """Every line end of `data` made LF: by plain replaces (a few times the regular
    expression's speed) where they pair CR and LF as LINE_END does, which is when one kind
    of pair, taken out, leaves none of the other kind."""
    if b"\r" not in data:
        return data
    for pair, other in ((b"\r\n", b"\n\r"), (b"\n\r", b"\r\n")):
        if other not in data or other not in data.replace(pair, b""):
            data = data.replace(pair, b"\n")
            return data.replace(b"\r", b"\n") if b"\r" in data else data
    return LINE_END.sub(b"\n", data)


def split_lines(chunks: Iterable[bytes]) -> Iterator[bytes]:
    """The lines of `chunks`, without their line ends; a last line without one counts."""
    ends = LineEnds()
    rest = b""
    for chunk in chunks:
        *ended, rest = (rest + ends.add(chunk)).split(b"\n")
        yield from ended
    *ended, rest = (rest + ends.end()).split(b"\n")
    yield from ended
    if rest:
        yield rest
