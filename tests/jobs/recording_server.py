"""What the webhook server of the tests records: each request it received, and where it listens."""

from __future__ import annotations

import json
from dataclasses import dataclass, field


@dataclass
class Received:
    """One request as the server saw it."""

    method: str
    path: str
    headers: dict[str, str]
    body: bytes

    def json(self) -> object:
        return json.loads(self.body)


@dataclass
class RecordingServer:
    """A loopback HTTP server that answers every POST with `status` and keeps the request."""

    port: int
    status: int = 204
    requests: list[Received] = field(default_factory=list)

    def url(self, path: str = "/hook") -> str:
        return f"http://127.0.0.1:{self.port}{path}"
