"""How failures become HTTP answers: the contract's JSON shape everywhere."""

from __future__ import annotations

import contextlib
import html
import logging
import re
from collections.abc import Generator, Iterable, Iterator, Sequence
from typing import Any
from urllib.parse import quote, unquote_plus

import anyio
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.datastructures import URL, Headers
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from jobs.auth.passwords import KEY_PREFIX, is_key_parameter
from jobs.errors import (
    ContractError,
    ErrorCode,
    library_status,
    resource_status,
    result,
    validation_summary,
)
from jobs.fleet.paths import MissingParameter

log = logging.getLogger(__name__)


def _not_json(request: Request, errors: Sequence[Any]) -> str | None:
    """Why a JSON body was not read, when it came under another type (curl's `-d` sends
    a form): FastAPI hands such a body on unparsed, and pydantic finds no fields in it."""
    sent_as = request.headers.get("content-type", "")
    unread = any(tuple(e.get("loc", ())) == ("body",) and isinstance(e.get("input"), bytes | str)
                 for e in errors)
    if not unread or "json" in sent_as.lower():
        return None
    return (f"body: read as JSON, send it with Content-Type: application/json (it came as "
            f"{sent_as or 'no Content-Type'})")


class CodedHTTPError(HTTPException):
    """An HTTP error status that carries one of the contract's error codes."""

    def __init__(self, status_code: int, code: ErrorCode, status_msg: str | None = None) -> None:
        super().__init__(status_code=status_code, detail=status_msg)
        self.code, self.status_msg = code, status_msg


def refused_whole(exc: ContractError) -> CodedHTTPError:
    """HTTP 422 with the contract's body: a request refused as a whole before anything is
    made (machines nobody registered, a selection that picks none)."""
    return CodedHTTPError(422, exc.code, exc.status_msg)


class AuthError(CodedHTTPError):
    """A missing (401) or wrong (403) API key, a revoked named key (401), or a key from an
    address locked out for wrong keys (429)."""


class KeysLockedOut(AuthError):
    """Every keyed request from an address that sent too many wrong keys, the right key too,
    until its lock-out ends (429, `Retry-After` in seconds)."""

    def __init__(self, status_msg: str, *, retry_after_s: int) -> None:
        super().__init__(429, ErrorCode.KEYS_LOCKED_OUT, status_msg)
        self.headers = {"Retry-After": str(retry_after_s)}


class RoleRefused(CodedHTTPError):
    """A known principal whose role or machines do not allow the operation (403)."""

    def __init__(self, status_msg: str) -> None:
        super().__init__(403, ErrorCode.ROLE_REFUSED, status_msg)


class DownloadBrokeOff(Exception):
    """A streamed answer failed after its headers went out.

    Nothing can be said in JSON any more: the connection is cut, so that the client sees an
    incomplete download, and the failure is logged once, as one line (`cut_short`).
    """


def cut_short(chunks: Iterable[bytes], what: str) -> Generator[bytes, None, None]:
    """The chunks of a streamed answer; a failure among them logged and made DownloadBrokeOff."""
    try:
        yield from chunks
    except (ContractError, OSError) as exc:  # a machine's or the disk's failure: expected
        log.warning("%s broke off; the client got an incomplete download: %s", what, exc)
        raise DownloadBrokeOff(what) from exc
    except Exception as exc:
        log.exception("%s broke off; the client got an incomplete download", what)
        raise DownloadBrokeOff(what) from exc


class ClosingStream(StreamingResponse):
    """A streamed answer whose generator is closed the moment the answer ends, however
    it ends.

    Starlette leaves the generator of a client that went away to the garbage collector,
    which a reference cycle keeps waiting a minute and more; what the generator does on
    its way out (backupFiles records the download aborted) is due now.
    """

    def __init__(self, content: Generator[bytes, None, None], **kwargs: Any) -> None:
        super().__init__(content, **kwargs)
        self._generator = content

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:  # no thread is in it: Starlette waits for a `next` under way to return
            with anyio.CancelScope(shield=True):
                await run_in_threadpool(self._generator.close)


class BodyTooLarge(HTTPException):
    """The request body is over the configured limit (413)."""

    def __init__(self, limit: int) -> None:
        super().__init__(status_code=413, detail=f"request body over {limit} bytes")


@contextlib.contextmanager
def resource_errors() -> Iterator[None]:
    """For dncq's own resources (machines, jobs, backups, schedules): one that does not
    exist is HTTP 404; a request it cannot take is 409, with the contract's error body."""
    try:
        yield
    except ContractError as exc:
        raise CodedHTTPError(resource_status(exc), exc.code, exc.status_msg) from None


@contextlib.contextmanager
def library_errors() -> Iterator[None]:
    """For the program library: a missing program, version or machine is HTTP 404, a bad
    name or reference 400, content too large for the operation 413, anything else refused 409."""
    try:
        yield
    except ContractError as exc:
        raise CodedHTTPError(library_status(exc), exc.code, exc.status_msg) from None


def install(app: FastAPI, *, contract_paths: Iterable[str]) -> None:
    """Register the handlers that give every failure the contract's body shape.

    `contract_paths`: the gateway contract's operations, whose refusals are HTTP 200.
    """
    contract = frozenset(contract_paths)

    @app.exception_handler(ContractError)
    async def contract_error(request: Request, exc: ContractError) -> JSONResponse:
        # The contract answers its own errors with HTTP 200 and the error body; a request
        # without a required parameter cannot be parsed at all: 400. dncq's own routes
        # (and OctoPrint's, which never says 200 for a failure) answer a refusal no route
        # gave its own status by its code (400 a bad parameter, 404 a missing thing, 413
        # too large, else 409), never 200, which a client takes for done.
        route = request.scope.get("route")
        if isinstance(exc, MissingParameter):
            status = 400
        elif getattr(route, "path", None) in contract:
            status = 200
        else:
            status = library_status(exc)
        return JSONResponse(exc.body(), status_code=status)

    @app.exception_handler(RequestValidationError)
    async def unparsable(request: Request, exc: RequestValidationError) -> JSONResponse:
        said = _not_json(request, exc.errors()) or validation_summary(exc.errors())
        return JSONResponse(result(ErrorCode.BAD_PARAMETER, said), status_code=400)

    @app.exception_handler(HTTPException)
    async def http_error(_: Request, exc: HTTPException) -> JSONResponse:
        if isinstance(exc, CodedHTTPError):
            code = exc.code
        elif exc.status_code == 413:
            code = ErrorCode.BODY_TOO_LARGE
        elif exc.status_code == 404:
            code = ErrorCode.PATH_NOT_FOUND
        else:
            code = ErrorCode.BAD_PARAMETER
        # A 401's detail is the bare phrase "Unauthorized" unless dncq gave it words (revoked).
        status_msg = exc.detail if isinstance(exc.detail, str) and exc.status_code != 401 \
            else getattr(exc, "status_msg", None)
        return JSONResponse(result(code, status_msg), status_code=exc.status_code,
                            headers=getattr(exc, "headers", None))

    @app.exception_handler(ClientDisconnect)
    async def client_gone(request: Request, _: ClientDisconnect) -> JSONResponse:
        # The client closed the connection mid-upload: its doing, and nothing was written.
        log.info("%s %s: the client went away before the whole body arrived",
                 request.method, request.url.path)
        return JSONResponse(result(ErrorCode.BAD_PARAMETER, "the body was cut off"),
                            status_code=400)

    @app.exception_handler(Exception)
    async def unexpected(_: Request, exc: Exception) -> JSONResponse:
        if not isinstance(exc, DownloadBrokeOff):  # logged already; its answer has begun
            log.exception("unexpected error")
        return JSONResponse(result(ErrorCode.INTERNAL_ERROR), status_code=500)


def _too_large(scope: Scope, limit: int) -> Response:
    """The 413 answer: the contract's body for the API; for a dashboard page's form, a page
    that says it, with the way back (a browser shows JSON as text, and no way on)."""
    headers = Headers(scope=scope)
    said = f"request body over {limit} bytes"
    if scope["path"].startswith("/api/") or "text/html" not in headers.get("accept", ""):
        return JSONResponse(result(ErrorCode.BODY_TOO_LARGE, said), status_code=413)
    back = URL(headers.get("referer", "/"))
    if back.netloc and back.netloc != headers.get("host"):
        back = URL("/")
    page = (f"<!doctype html><title>Too large</title><h1>Too large</h1><p>The file sent is "
            f"larger than the dashboard takes ({limit // (1024 * 1024)} MB). Send a larger "
            f"program with <code>dncq send</code> or the API's <code>sendFileStream</code>."
            f'</p><p><a href="{html.escape(back.path + ("?" + back.query if back.query else ""))}">'
            f"Back</a></p>")
    return HTMLResponse(page, status_code=413)


class BodyLimit:
    """Refuse request bodies over a limit before they are read whole (ASGI middleware).

    Paths in `stream_paths` take the stream limit, every other path the JSON limit; a
    `{name}` in one stands for one step (`/machines/{machine_id}/api/files/local`).
    """

    def __init__(self, app: ASGIApp, *, json_limit: int, stream_limit: int,
                 stream_paths: Iterable[str]) -> None:
        self.app = app
        self.json_limit = json_limit
        self.stream_limit = stream_limit
        self.stream_paths = re.compile("|".join(
            "/".join("[^/]+" if step.startswith("{") else re.escape(step)
                     for step in path.split("/")) for path in stream_paths))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        streamed = self.stream_paths.fullmatch(scope["path"]) is not None
        limit = self.stream_limit if streamed else self.json_limit
        for name, value in scope.get("headers", []):
            if name == b"content-length" and value.isdigit() and int(value) > limit:
                await _too_large(scope, limit)(scope, receive, send)
                return
        received = 0

        async def limited() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise BodyTooLarge(limit)
            return message

        await self.app(scope, limited, send)


_MASK = "***"


# A key this short is masked as a parameter's value only: searched for in the whole line, a
# one-letter key would mask that letter in every word ("api***ey").
MIN_SEARCHED_KEY_CHARS = 8
# A named key, wherever it stands (under a misspelt parameter, in a path): its shape is
# known (`passwords.new_key`), its value is not kept anywhere the log could compare with.
_NAMED_KEY = re.compile(re.escape(KEY_PREFIX) + r"[A-Za-z0-9_-]{20,}")


class _HideApiKey(logging.Filter):
    """Masks API keys in access log lines: the value of a parameter whose decoded name is
    `apikey` (`api%6Bey` reaches the same check), any value equal to a configured key, and
    anything shaped as a named key."""

    def __init__(self) -> None:
        super().__init__()
        self.keys: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(self.masked(a) if isinstance(a, str) else a
                                for a in record.args)
        return True

    def masked(self, text: str) -> str:
        """`text` (a path with its query) with every key in it masked."""
        path, question, query = text.partition("?")
        if question:
            params = []
            for param in query.split("&"):
                name, equals, value = param.partition("=")
                if equals and (is_key_parameter(name) or unquote_plus(value) in self.keys):
                    param = f"{name}={_MASK}"
                params.append(param)
            text = f"{path}?{'&'.join(params)}"
        for key in self.keys:  # a key anywhere else, as typed or percent-encoded
            if len(key) >= MIN_SEARCHED_KEY_CHARS:
                text = text.replace(key, _MASK).replace(quote(key, safe=""), _MASK)
        return _NAMED_KEY.sub(_MASK, text)


class _QuietBrokeOff(logging.Filter):
    """Drops the server's traceback of a download that broke off, logged already."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.exc_info and isinstance(record.exc_info[1], DownloadBrokeOff))


def quiet_broken_downloads() -> None:
    """Keep uvicorn from logging a traceback for each download that broke off."""
    server_log = logging.getLogger("uvicorn.error")
    if not any(isinstance(f, _QuietBrokeOff) for f in server_log.filters):
        server_log.addFilter(_QuietBrokeOff())


def hide_keys_in_access_log(keys: Iterable[str | None] = ()) -> None:
    """Keep API keys out of uvicorn's access log: `?apikey=` however written, and `keys`."""
    access = logging.getLogger("uvicorn.access")
    hiding = next((f for f in access.filters if isinstance(f, _HideApiKey)), None)
    if hiding is None:
        hiding = _HideApiKey()
        access.addFilter(hiding)
    hiding.keys.update(k for k in keys if k)
