"""HTTP failures (httpx) as transport errors: the one mapping the HTTP transports share."""

from __future__ import annotations

import contextlib
import re
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import IO, Annotated, cast

import httpx
from pydantic import AfterValidator, HttpUrl

from worker.transports.base import (
    CHUNK_BYTES,
    BadPath,
    Busy,
    ConnectFailed,
    Deadline,
    Dropped,
    Exists,
    NetworkOptions,
    NotFound,
    Permanent,
    PermissionDenied,
    ProgressFn,
    TimedOut,
    Transient,
    TransportError,
)

SPOOL_MAX_BYTES = 8 * 1024 * 1024  # uploads above this are spooled to a temporary file


def _without_credentials(url: HttpUrl) -> HttpUrl:
    # A user and password in the URL would be stored unsealed and shown to every viewer of
    # the machine; the server's key goes in `api_key`, which is sealed and never shown.
    if url.username or url.password:
        raise ValueError("url must not carry credentials; give the key as api_key")
    if url.query or url.fragment:  # `?apikey=` too, which no request sends: paths replace it
        raise ValueError("url must not carry a query or fragment; give the key as api_key")
    return url


ServerUrl = Annotated[HttpUrl, AfterValidator(_without_credentials)]
"""The base URL of a file server reached over HTTP: http(s), a host, no credentials."""

BY_STATUS: Mapping[int, type[TransportError]] = {
    400: BadPath,
    401: PermissionDenied,
    403: PermissionDenied,
    404: NotFound,
    409: Exists,
    415: BadPath,  # a file type the server does not take
    429: Busy,
    503: Busy,
}


def network_client(options: NetworkOptions, *, base_url: str | httpx.URL,
                   headers: Mapping[str, str], verify: bool = True) -> httpx.Client:
    """An httpx client with the machine's timeouts: `timeout_s` on each socket operation,
    `transfer_timeout_s` on each request from its body's first byte to its answer's last.

    httpx's timeouts apply to each socket read or write alone, so a server that trickles a
    byte at a time, or reads an upload that slowly, never times out; event hooks put a
    deadline on the body's and the answer's chunks instead. Hooks, not a transport of our
    own: that would turn off the proxies the environment names.
    """
    seconds = options.transfer_timeout_s

    def start(request: httpx.Request) -> None:
        deadline = request.extensions[_DEADLINE] = Deadline(seconds)
        body = cast(httpx.SyncByteStream, request.stream)  # a sync client's
        request.stream = _CheckedStream(body, deadline, request)

    def check_chunks(response: httpx.Response) -> None:
        deadline = response.request.extensions[_DEADLINE]
        stream = cast(httpx.SyncByteStream, response.stream)  # a sync client's
        response.stream = _CheckedStream(stream, deadline, response.request)

    return httpx.Client(base_url=base_url, headers=headers, timeout=options.timeout_s,
                        verify=verify,
                        event_hooks={"request": [start], "response": [check_chunks]})


_DEADLINE = "dncq.deadline"  # the request's Deadline, in its extensions


class _TooLong(httpx.TimeoutException):
    """An upload still being sent, or an answer still arriving, at its deadline."""


class _CheckedStream(httpx.SyncByteStream):
    """A request's body or its answer in chunks, ended with _TooLong at the request's
    deadline."""

    def __init__(self, inner: httpx.SyncByteStream, deadline: Deadline,
                 request: httpx.Request) -> None:
        self._inner = inner
        self._deadline = deadline
        self._request = request

    def __iter__(self) -> Iterator[bytes]:
        for chunk in self._inner:
            if self._deadline.passed():
                raise _TooLong(self._deadline.missed, request=self._request)
            yield chunk

    def close(self) -> None:
        self._inner.close()


@contextlib.contextmanager
def http_errors(
    what: str, *, by_status: Mapping[int, type[TransportError]] | None = None,
    clean: Callable[[str], str] = str,
) -> Iterator[None]:
    """Raise the transport error for an httpx failure inside the block.

    Args:
        what: the path or URL named in the message.
        by_status: statuses that mean something else for this one request.
        clean: applied to every message (a transport whose key might be echoed blanks it).
    """
    try:
        yield
    except httpx.HTTPError as exc:
        error, message = _saying(exc, what, by_status or {})
        raise error(clean(_without_secrets(message, exc))) from exc


def _saying(exc: httpx.HTTPError, what: str, by_status: Mapping[int, type[TransportError]]
            ) -> tuple[type[TransportError], str]:
    """The transport error class for an httpx failure, and its message."""
    if isinstance(exc, httpx.HTTPStatusError):
        status = exc.response.status_code
        error = by_status.get(status) or BY_STATUS.get(status)
        if error is None:
            error = Transient if status >= 500 else TransportError
        return error, f"{what}: HTTP {status} {_reason(exc.response)}"
    if isinstance(exc, _TooLong):
        return TimedOut, f"{what}: {exc}"
    if isinstance(exc, httpx.ConnectTimeout):
        return TimedOut, f"{what}: connect timed out"
    if isinstance(exc, httpx.TimeoutException):
        return TimedOut, f"{what}: no answer in time"
    if isinstance(exc, httpx.ConnectError | httpx.ProxyError):
        return ConnectFailed, f"{what}: cannot connect ({exc})"
    if isinstance(exc, httpx.UnsupportedProtocol):  # a URL no retry can make usable
        return BadPath, f"{what}: {exc}"
    if isinstance(exc, httpx.TransportError):  # read/write errors, a peer that hung up
        return Dropped, f"{what}: connection lost ({exc})"
    return Permanent, f"{what}: {exc}"  # an answer we cannot use: undecodable, redirects


_SECRET_HEADERS = ("x-api-key", "authorization")


def _without_secrets(text: str, exc: httpx.HTTPError) -> str:
    """`text` with every credential the request sent blanked, in any letter case: a
    server's error text may echo the key (\"Invalid API key …\")."""
    try:
        headers = exc.request.headers
    except RuntimeError:  # an error raised before any request was made
        return text
    for name in _SECRET_HEADERS:
        for value in headers.get_list(name):
            for secret in {value, value.split(" ", 1)[-1]}:  # "Bearer <token>" too
                if len(secret) >= 4:
                    text = re.sub(re.escape(secret), "***", text, flags=re.IGNORECASE)
    return text


def _reason(response: httpx.Response) -> str:
    """The server's own error text when it gives one in JSON, else the status phrase."""
    try:
        error = response.json().get("error")
    except (ValueError, AttributeError, httpx.StreamError):  # not JSON, or a stream not read
        error = None
    if isinstance(error, dict):  # Moonraker: {"error": {"code": …, "message": …}}
        error = error.get("message")
    return str(error or response.reason_phrase)[:200]


def clean_path(path: str) -> str:
    """A server path without empty, `.` or `..` parts (BadPath for the last two)."""
    parts = [p for p in path.split("/") if p]
    if any(p in (".", "..") for p in parts):
        raise BadPath(f"relative parts in path: {path!r}")
    return "/".join(parts)


@contextlib.contextmanager
def spooled_upload(chunks: Iterable[bytes], progress: ProgressFn | None
                   ) -> Iterator[tuple[IO[bytes], int]]:
    """The upload copied into a local spool (multipart needs a file) and its size.

    Spooled first, so that a source failing midway never reaches the server; in memory up
    to `SPOOL_MAX_BYTES`, in a temporary file above.
    """
    with tempfile.SpooledTemporaryFile(max_size=SPOOL_MAX_BYTES) as spool:
        done = 0
        for chunk in chunks:
            spool.write(chunk)
            done += len(chunk)
            if progress:
                progress(done, None)
        spool.seek(0)
        yield spool, done


def streamed_get(client: httpx.Client, url: str | httpx.URL,
                 errors: Callable[[], contextlib.AbstractContextManager[None]]
                 ) -> httpx.Response:
    """A GET whose body is read later (`body_chunks`); closed at once on an error status."""
    with errors():
        response = client.send(client.build_request("GET", url), stream=True)
        try:
            response.raise_for_status()
        except BaseException:
            response.close()
            raise
    return response


def body_chunks(response: httpx.Response, *,
                errors: Callable[[], contextlib.AbstractContextManager[None]],
                total: int | None, progress: ProgressFn | None) -> Iterator[bytes]:
    """The body of a `streamed_get` in chunks, with progress; the response closed after."""
    done = 0
    try:
        with errors():
            for chunk in response.iter_bytes(CHUNK_BYTES):
                done += len(chunk)
                yield chunk
                if progress:
                    progress(done, total)
    finally:
        response.close()
