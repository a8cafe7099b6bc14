"""A request's key and role are settled before its body is read: the body of a client
without a right key, or of a role the route refuses, is never parsed (20 MB of JSON took
500 MB and seconds to parse for a 401)."""

from __future__ import annotations

import json
from typing import Any

import anyio
import pytest

from jobs.auth.roles import Role
from tests.conftest import API_KEY

MACHINE = {"id": "m9", "name": "Nine", "model": "Mock"}


def posted(app: Any, path: str, body: bytes, key: str | None) -> tuple[int, bool]:
    """The HTTP status of a POST of `body` through the whole app, and whether it read the body."""
    read = False
    status = 0

    async def receive() -> dict[str, Any]:
        nonlocal read
        read = True
        return {"type": "http.request", "body": body, "more_body": False}

    async def send(message: dict[str, Any]) -> None:
        nonlocal status
        if message["type"] == "http.response.start":
            status = message["status"]

    headers = [(b"content-type", b"application/json"),
               (b"content-length", str(len(body)).encode())]
    if key is not None:
        headers.append((b"x-api-key", key.encode()))
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
             "method": "POST", "scheme": "http", "path": path, "raw_path": path.encode(),
             "query_string": b"", "root_path": "", "headers": headers,
             "client": ("127.0.0.1", 50000), "server": ("127.0.0.1", 80)}
    anyio.run(app, scope, receive, send)
    return status, read


@pytest.mark.parametrize(("who", "status"), [(None, 401), ("not-a-key-of-this-dncq", 403),
                                             ("viewer", 403), ("programmer", 403)])
def test_a_body_sent_without_a_right_key_or_role_is_refused_unread(
        api, keys, who, status) -> None:
    key = keys[Role(who)] if who in ("viewer", "programmer") else who

    answer = posted(api.app, "/api/machines", json.dumps(MACHINE).encode(), key)

    assert answer == (status, False)
    assert api.get("/api/machines/m9", headers={"X-Api-Key": API_KEY}).status_code == 404


@pytest.mark.parametrize("who", ["admin", "admin key"])
def test_a_body_sent_with_a_key_of_the_routes_role_is_read(api, keys, who) -> None:
    key = keys[Role.ADMIN] if who == "admin" else API_KEY

    assert posted(api.app, "/api/machines", json.dumps(MACHINE).encode(), key) == (201, True)


def a_send_job(size_bytes: int) -> bytes:
    """A send job's JSON of about `size_bytes`, its program in `content`."""
    return json.dumps({"kind": "send", "content": "G1 X1\n" * (size_bytes // 7),
                       "targets": [{"machineID": "1010", "fileName": "O1"}]}).encode()


def test_a_viewer_is_refused_a_job_before_its_body_is_read(api, keys) -> None:
    # No kind of job is a viewer's: its 403 needs no body, however large the body is.
    status, read = posted(api.app, "/api/jobs", a_send_job(18_000_000), keys[Role.VIEWER])

    assert (status, read) == (403, False)


def test_an_operators_job_is_read_and_refused_by_its_kind(api, keys) -> None:
    status, read = posted(api.app, "/api/jobs", a_send_job(100), keys[Role.OPERATOR])

    assert (status, read) == (403, True)
