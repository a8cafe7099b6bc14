"""The check of a file against dncq's limits before `dncq send FILE`, `dncq library add` and
`dncq run FILE` send it: made on the connection the file then goes on, asking neither
dncq's database nor its broker."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from starlette.types import ASGIApp, Receive, Scope, Send

from jobs.api.app import create_app
from jobs.settings import Settings
from tests.jobs.cli.runner import dncq
from tests.jobs.conftest import cli_elsewhere
from tests.jobs.parts_asked import parts_asked
from tests.servers import RedisServer, free_port

LIMIT_BYTES = 2048  # of a JSON body and of a stream, at the dncq these tests serve


class SeenRequests:
    """An app that notes each request's connection (the client's address), method and path."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.seen: list[tuple[Any, str, str]] = []

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            self.seen.append((scope["client"], scope["method"], scope["path"]))
        await self.app(scope, receive, send)

    def connection_of(self, method: str, path: str) -> Any:
        """The one connection `method path` came on."""
        [connection] = [c for c, m, p in self.seen if (m, p) == (method, path)]
        return connection


@pytest.fixture
def served(settings: Settings, own_broker: RedisServer, add_machines: Callable[..., Any],
           monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[SeenRequests]:
    """A dncq with `own_broker` and bodies limited to LIMIT_BYTES, served on loopback, machine
    2001 in its fleet (a DNC control nothing listens for: only plans are asked of it); the
    CLI pointed at it from an empty folder. Yields the requests it sees."""
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": free_port()}})
    limited = settings.model_copy(update={
        "broker_url": own_broker.url, "max_json_body_bytes": LIMIT_BYTES,
        "max_stream_body_bytes": LIMIT_BYTES})
    requests = SeenRequests(create_app(limited))
    with cli_elsewhere(requests, monkeypatch, tmp_path):
        yield requests


# Each command, with {file} for its file, and the path its file is sent to.
UPLOADS = {
    "send": (("send", "{file}", "--to", "2001", "--dry-run"), "/api/jobs"),
    "library add": (("library", "add", "{file}", "--folder", "VIPROS"), "/api/library/programs"),
    "run": (("run", "2001", "{file}", "--dry-run"), "/api/programs"),
}


@pytest.mark.parametrize("command", UPLOADS)
def test_the_limits_are_asked_on_the_connection_the_file_then_goes_on(
        served: SeenRequests, program: Path, command: str) -> None:
    # library add and run opened a second connection to dncq for the upload.
    args, upload_path = UPLOADS[command]

    result = dncq(*(arg.format(file=program) for arg in args))

    assert result.exit_code == 0, result.output
    assert served.connection_of("GET", "/api/health") == served.connection_of(
        "POST", upload_path)


# What each command says of a file over LIMIT_BYTES, the words it said before.
REFUSED = f"error: 20013 Request body is too large: request body over {LIMIT_BYTES} bytes"


@pytest.mark.parametrize("command", ["send", "library add"])
def test_a_file_over_the_limit_is_refused_without_asking_dncqs_database_or_broker(
        served: SeenRequests, own_broker: RedisServer, tmp_path: Path, command: str) -> None:
    # The limits came with dncq's whole health report: a statement, a query of the runs
    # and a connection to the broker (2 s more before the refusal when it was down).
    large = tmp_path / "LARGE.NC"
    large.write_bytes(b"G0 X0\n" * LIMIT_BYTES)
    args, upload_path = UPLOADS[command]

    with parts_asked(own_broker) as asked:
        result = dncq(*(arg.format(file=large) for arg in args))

    assert result.exit_code == 1
    assert " ".join(result.output.split()).startswith(REFUSED)
    assert (asked.statements, asked.broker_connections) == ([], 0)
    assert [(m, p) for _, m, p in served.seen] == [("GET", "/api/health")]  # nothing sent
