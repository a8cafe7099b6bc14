"""The gateway contract's names in any case, as the gateway's own routing takes them: its
paths (`/api/cnc/ReadProgramList`) and its query parameters (`DirAtCNC`, `machineid`).

Renamed in one ASGI middleware, outermost, so that every layer within (the audit trail, the
body limit, the routes) sees the names as the contract writes them. An unknown path was 404
with 158, "Path is not found.", which a client reads as a missing file; an unknown parameter
was left out, and `deleteFile?fileName=A.nc&DirAtCNC=1` deleted the root's `A.nc`.
"""

from __future__ import annotations

from collections.abc import Iterable
from urllib.parse import unquote_to_bytes

from starlette.types import ASGIApp, Receive, Scope, Send

# The contract's query parameters, by their names in lower case.
CONTRACT_QUERY = {name.lower(): name for name in (
    "machineID", "fileName", "dirAtCNC", "subDir", "dirName", "isLock", "lockStart", "lockEnd")}


def query_spelled(query: bytes) -> bytes:
    """`query` with the contract's parameters named as the contract names them, however
    written (`DirAtCNC`, `machineid`); one also given in its own spelling is left to it."""
    pairs = [pair.partition(b"=") for pair in query.split(b"&")]
    names = [unquote_to_bytes(name.replace(b"+", b" ")).decode("utf-8", "replace")
             for name, _, _ in pairs]
    spelled = []
    for (raw, eq, value), name in zip(pairs, names, strict=True):
        own = CONTRACT_QUERY.get(name.lower())
        if own and own != name and own not in names:
            raw = own.encode()
        spelled.append(raw + eq + value)
    return b"&".join(spelled)


class ContractSpelling:
    """A request to one of the contract's `paths`, its path and query named as the contract
    writes them (ASGI middleware)."""

    def __init__(self, app: ASGIApp, paths: Iterable[str]) -> None:
        self.app = app
        self.by_key = {path.lower(): path for path in paths}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            own = self.by_key.get(scope["path"].lower())
            if own is not None:
                scope = {**scope, "path": own, "raw_path": own.encode(),
                         "query_string": query_spelled(scope.get("query_string", b""))}
        await self.app(scope, receive, send)
