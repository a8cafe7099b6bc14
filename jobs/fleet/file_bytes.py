"""A file's bytes as the contract gives them: text (`content` and its `encoding`) or `base64`
in 2.6.3's body; and whether two streams of chunks hold the same bytes, however each is cut.
"""

from __future__ import annotations

import base64
from collections.abc import Iterable, Iterator

_TEXT_CONTROL_OK = {9, 10, 12, 13, 26}  # tab, LF, FF, CR, SUB (EOF mark of old controllers)


def as_json_content(data: bytes, *, encoding: str) -> dict[str, str]:
    """2.6.3's body: `content`+`encoding` when the bytes are text (ASCII, or the machine's
    `encoding`), else `base64`."""
    if not any(b < 32 and b not in _TEXT_CONTROL_OK for b in data):
        if data.isascii():
            return {"content": data.decode("ascii"), "encoding": "us-ascii"}
        try:
            return {"content": data.decode(encoding), "encoding": encoding}
        except UnicodeDecodeError:
            pass
    return {"base64": base64.b64encode(data).decode("ascii")}


def same_bytes(first: Iterable[bytes], second: Iterable[bytes]) -> bool:
    """Whether two streams of chunks hold the same bytes, however each is cut."""
    a, b = iter(first), iter(second)
    held_a: memoryview | None = memoryview(b"")
    held_b: memoryview | None = memoryview(b"")
    while True:
        held_a = held_a or _more(a)
        held_b = held_b or _more(b)
        if held_a is None or held_b is None:
            return held_a is None and held_b is None
        n = min(len(held_a), len(held_b))
        if held_a[:n] != held_b[:n]:
            return False
        held_a, held_b = held_a[n:], held_b[n:]


def _more(chunks: Iterator[bytes]) -> memoryview | None:
    """The next chunk that is not empty; None at the end."""
    for chunk in chunks:
        if chunk:
            return memoryview(chunk)
    return None
