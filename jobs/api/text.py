"""Request text that is not Unicode is refused at the edge; stored text never breaks an answer.

JSON may write lone surrogates (`"\\ud800"`) and a URL may carry bytes that are not UTF-8
(`%ED%A0%80`, `%FF`): neither is text a machine, the database or a JSON answer can hold.
Every route is a `CheckedRoute`, which answers such a request with HTTP 400 and the
contract's 20001 before the route runs. `TextSafeJSON` writes any text that got into a
record before this check existed as U+FFFD, so that no stored record can fail a read.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Coroutine, Mapping
from typing import Any
from urllib.parse import unquote_to_bytes

from fastapi import Request, Response
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute

from jobs.api.deps import authorized_before_body, role_checks
from jobs.api.errors import CodedHTTPError
from jobs.errors import ErrorCode

_SURROGATE = re.compile("[\ud800-\udfff]")
_MAX_DEPTH = 64  # deeper JSON is no request of ours; the walk stays bounded


class NotText(CodedHTTPError):
    """A request parameter or body field that is not valid Unicode (HTTP 400, 20001)."""

    def __init__(self, where: str, what: str) -> None:
        super().__init__(400, ErrorCode.BAD_PARAMETER, f"{where}: {what}")


def not_text_in(value: Any, where: str = "body", depth: int = 0) -> str | None:
    """Where in parsed JSON `value` a string (or key) holds a lone surrogate, or None."""
    if isinstance(value, str):
        return None if _is_text(value) else where
    if depth > _MAX_DEPTH:
        return None
    if isinstance(value, dict):
        for key, item in value.items():
            if isinstance(key, str) and not _is_text(key):
                return f"{where} (a key)"
            found = not_text_in(item, f"{where}.{key}", depth + 1)
            if found:
                return found
    elif isinstance(value, list):
        for index, item in enumerate(value):
            found = not_text_in(item, f"{where}[{index}]", depth + 1)
            if found:
                return found
    return None


def _is_text(value: str) -> bool:
    if value.isascii():  # the usual case, and a 10 MB program's: no copy made
        return True
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:  # only a surrogate cannot be written in UTF-8
        return False
    return True


def check_url(scope: Mapping[str, Any]) -> None:
    """Refuse a path or query whose percent-decoded bytes are not UTF-8.

    Raises:
        NotText: naming the query parameter or the path.
    """
    raw_path = scope.get("raw_path") or b""
    if not _is_utf8(unquote_to_bytes(raw_path.split(b"?", 1)[0])):
        raise NotText("path", "not valid UTF-8")
    query: bytes = scope.get("query_string") or b""
    for pair in query.split(b"&"):
        name, _, value = pair.replace(b"+", b" ").partition(b"=")
        if not _is_utf8(unquote_to_bytes(name)):
            raise NotText("query", "a parameter name is not valid UTF-8")
        if not _is_utf8(unquote_to_bytes(value)):
            shown = unquote_to_bytes(name).decode("utf-8")
            raise NotText(shown, "not valid UTF-8")


def _is_utf8(data: bytes) -> bool:
    try:
        data.decode("utf-8")  # strict: encoded surrogates (ED A0 80) are refused too
    except UnicodeDecodeError:
        return False
    return True


class CheckedRequest(Request):
    """A request whose JSON body is refused when it holds text that is not Unicode."""

    async def json(self) -> Any:
        """The parsed body; NotText when a string or key holds a lone surrogate."""
        parsed = await super().json()
        where = not_text_in(parsed)
        if where:
            raise NotText(where, "not valid Unicode (a lone surrogate such as \\ud800)")
        return parsed


class CheckedRoute(APIRoute):
    """A route that checks its URL and JSON body for text that is not Unicode first, and
    who asks before it reads a body (`jobs.api.deps.authorized_before_body`)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        """The route's handler, behind the checks."""
        handler = super().get_route_handler()
        checks = role_checks(self)
        reads_body = self.body_field is not None

        async def checked(request: Request) -> Response:
            check_url(request.scope)
            if reads_body:
                await authorized_before_body(request, checks)
            return await handler(CheckedRequest(request.scope, request.receive))

        return checked


class TextSafeJSON(JSONResponse):
    """JSON answers that any stored string can be written in: a lone surrogate shows as U+FFFD."""

    def render(self, content: Any) -> bytes:
        """The body; a string that is not Unicode written with U+FFFD in its place."""
        try:
            return super().render(content)
        except UnicodeEncodeError:
            text = json.dumps(content, ensure_ascii=False, allow_nan=False, indent=None,
                              separators=(",", ":"))
            return _SURROGATE.sub("\ufffd", text).encode("utf-8")
