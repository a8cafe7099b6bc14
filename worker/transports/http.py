"""HTTP failures (httpx) as transport errors: the one mapping the HTTP transports share."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import IO

import httpx

from worker.transports.base import (
    BadPath,
    Busy,
    ConnectFailed,
    Dropped,
    Exists,
    NotFound,
    Permanent,
    PermissionDenied,
    ProgressFn,
    TimedOut,
    Transient,
    TransportError,
)

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
    except httpx.HTTPStatusError as exc:
        status = exc.response.status_code
        error = (by_status or {}).get(status) or BY_STATUS.get(status)
        if error is None:
            error = Transient if status >= 500 else TransportError
        raise error(clean(f"{what}: HTTP {status} {_reason(exc.response)}")) from exc
    except httpx.ConnectTimeout as exc:
        raise TimedOut(clean(f"{what}: connect timed out")) from exc
    except httpx.TimeoutException as exc:
        raise TimedOut(clean(f"{what}: no answer in time")) from exc
    except (httpx.ConnectError, httpx.ProxyError) as exc:
        raise ConnectFailed(clean(f"{what}: cannot connect ({exc})")) from exc
    except httpx.UnsupportedProtocol as exc:  # a URL no retry can make usable
        raise BadPath(clean(f"{what}: {exc}")) from exc
    except httpx.TransportError as exc:  # read/write errors, a peer that hung up
        raise Dropped(clean(f"{what}: connection lost ({exc})")) from exc
    except httpx.HTTPError as exc:  # an answer we cannot use: undecodable, endless redirects
        raise Permanent(clean(f"{what}: {exc}")) from exc


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


def spool_upload(chunks: Iterable[bytes], spool: IO[bytes], progress: ProgressFn | None) -> int:
    """Copy an upload into a local spool (multipart needs a file), reporting progress."""
    done = 0
    for chunk in chunks:
        spool.write(chunk)
        done += len(chunk)
        if progress:
            progress(done, None)
    return done
