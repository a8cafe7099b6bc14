"""A JSON request body that carries a file as Base64, streamed: the file read and encoded a
piece at a time, never whole in memory, with the body's exact length declared first."""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

# A multiple of 3 bytes: the Base64 of pieces this size, joined, is the Base64 of the whole.
BASE64_PIECE_BYTES = 3 * 256 * 1024


class FileChanged(Exception):
    """The file shrank or grew while it was sent: the body would be shorter than it said,
    or carry a program cut short. Raised before the body's end, so the request is never
    whole and nothing is queued."""


class FileBody:
    """`request` as JSON with `key` holding `file`'s bytes in Base64.

    Its `length_bytes` is known before a byte of the file is read: the CLI checks it
    against the API's limit first, and the API refuses a body over it from the
    Content-Length header alone (20013), so a file too large costs no memory here. The
    file's size is read once; that many bytes are sent, and a file that is not that size
    by the end is FileChanged.
    """

    def __init__(self, request: dict[str, Any], *, key: str, file: Path) -> None:
        self.file = file
        self.size_bytes = file.stat().st_size
        fields = json.dumps(request, separators=(",", ":"))[1:-1]
        self.head = ("{" + fields + ("," if fields else "") + json.dumps(key) + ':"').encode()
        self.tail = b'"}'
        encoded_bytes = 4 * -(-self.size_bytes // 3)  # Base64: 4 characters per 3 bytes begun
        self.length_bytes = len(self.head) + encoded_bytes + len(self.tail)

    def headers(self) -> dict[str, str]:
        """The headers that say what the body is and how long."""
        return {"content-type": "application/json", "content-length": str(self.length_bytes)}

    def __iter__(self) -> Iterator[bytes]:
        yield self.head
        left_bytes = self.size_bytes
        with open(self.file, "rb") as source:
            while left_bytes:
                piece = source.read(min(BASE64_PIECE_BYTES, left_bytes))
                if not piece:
                    raise FileChanged(f"{self.file} shrank while it was sent")
                left_bytes -= len(piece)
                yield base64.b64encode(piece)
            # Bytes past the size read first: a file still being written, or one whose size
            # says nothing (/proc's 0): sent, it would be a program cut short.
            if source.read(1):
                raise FileChanged(f"{self.file} grew while it was sent")
        yield self.tail
