"""A small HTTP client of dncq's own API, for the CLI."""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from typing import Any

import httpx

from jobs import VERSION_HEADER
from jobs.local_times import local_text
from jobs.settings import API_KEY_FILE, Settings


class ApiError(Exception):
    """The API answered with an error (contract error or HTTP failure)."""

    def __init__(self, message: str, *, code: int | None = None,
                 status_msg: str | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.status_msg = status_msg

    @property
    def refused_selection(self) -> bool:
        """A job refused whole because its selection names ids or tags that are not there."""
        return (self.code in (10003, 20001)
                and (self.status_msg or "").endswith(REFUSED_SELECTION_END))

    @property
    def body_too_large(self) -> bool:
        """A request over the API's limit of its body (20013)."""
        return self.code == BODY_TOO_LARGE

    @property
    def exit_code(self) -> int:
        """The CLI's exit status for this refusal: LOCKED_OUT_EXIT for a locked-out address,
        which the same command gets past once the lock-out ends; else 1."""
        return LOCKED_OUT_EXIT if self.code == KEYS_LOCKED_OUT else 1


# How the API's refusal of a selection with unknown ids or tags ends (jobs.rollout).
REFUSED_SELECTION_END = "nothing was queued"
BODY_TOO_LARGE = 20013  # jobs.errors.ErrorCode.BODY_TOO_LARGE, whose module loads more
BODY_TOO_LARGE_MSG = "Request body is too large"  # its errorMsg, without the full stop
KEYS_LOCKED_OUT = 20429  # jobs.errors.ErrorCode.KEYS_LOCKED_OUT: every key from here refused
# sysexits' EX_TEMPFAIL: a script can tell "wait until the lock-out ends" from a failure (1),
# a usage error (2) and a Ctrl-C (130), and must not retry sooner: each try is refused too.
LOCKED_OUT_EXIT = 75
# The address in the statusMsg of jobs.api.key_lockout (`came from 10.0.0.7: every key`).
_LOCKED_ADDRESS = re.compile(r"came from (\S+): every key")


CONNECT_TIMEOUT_S = 10.0  # a dncq that runs accepts at once, however busy


class Client:
    """Calls the API at the settings' URL with the settings' key."""

    def __init__(self, settings: Settings, *, timeout_s: float = 600.0) -> None:
        headers = {}
        key = settings.effective_api_key()
        if key:
            headers["X-Api-Key"] = key
        # A long wait for an answer (a check of the whole fleet, a large backup verified), a
        # short one for the connection: a host that is down or drops it left the command
        # hanging for minutes before it said it could not reach dncq.
        self.http = httpx.Client(base_url=settings.api_url, headers=headers,
                                 timeout=httpx.Timeout(timeout_s, connect=CONNECT_TIMEOUT_S))
        self.key_hint = key_source(settings)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.http.close()

    def call(self, method: str, path: str, **kwargs: Any) -> Any:
        """JSON answer of one request; raises ApiError for contract errors and HTTP errors."""
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise ApiError(self._unreachable(exc)) from exc
        return checked(response, key_hint=self.key_hint)

    def refuse_over_the_limit(self, length_bytes: int, *, limit: str) -> None:
        """ApiError, as the API words it, when a body of `length_bytes` is over the API's
        `limit` (a name in `/api/health`'s `limits`), before a byte of it is sent: the API
        refuses it from its length, but only once the whole body has come in. A dncq older
        than `limits` says nothing here, and refuses it after it was sent."""
        # `only=limits` asks neither dncq's database nor its broker; a dncq older than it
        # answers its whole report, which `workers=false` keeps from pinging the workers.
        answer = self.call("GET", "/api/health", params={"only": "limits", "workers": "false"})
        limits = answer.get("limits") if isinstance(answer, dict) else None
        limit_bytes = limits.get(limit) if isinstance(limits, dict) else None
        if isinstance(limit_bytes, int) and length_bytes > limit_bytes:
            said = f"request body over {limit_bytes} bytes"  # jobs.api.errors.BodyLimit's
            raise ApiError(f"{BODY_TOO_LARGE} {BODY_TOO_LARGE_MSG}: {said}",
                           code=BODY_TOO_LARGE, status_msg=said)

    def call_text(self, method: str, path: str, **kwargs: Any) -> str:
        """The text of one answer (CSV); raises ApiError as `call` does."""
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise ApiError(self._unreachable(exc)) from exc
        if response.is_error:  # a CSV is no JSON: only an error is read as one
            checked(response, key_hint=self.key_hint)
        refuse_another_api(response)
        return response.text

    @contextlib.contextmanager
    def stream(self, method: str, path: str, **kwargs: Any) -> Iterator[httpx.Response]:
        """A streamed answer, closed afterwards; raises ApiError when dncq cannot be reached."""
        request = self.http.build_request(method, path, **kwargs)
        try:
            response = self.http.send(request, stream=True)
        except httpx.TransportError as exc:
            raise ApiError(self._unreachable(exc)) from exc
        try:
            yield response
        finally:
            response.close()

    def _unreachable(self, exc: Exception) -> str:
        return (f"cannot reach dncq at {self.http.base_url} ({exc or type(exc).__name__}); "
                "is it running there? DNCQ_URL, or DNCQ_PORT as dncq serve was started "
                "with, says where the CLI looks")


def refuse_a_page(response: httpx.Response) -> None:
    """ApiError when a web page answered: dncq's API answers JSON or a file, never HTML, so
    DNCQ_URL points at another server (or at a proxy's error page); its HTML is not shown."""
    kind = response.headers.get("content-type", "")
    if kind.startswith("text/html"):
        raise ApiError(f"{response.url} answered HTTP {response.status_code} with a web page "
                       f"({kind.split(';')[0]}), not dncq's answer: DNCQ_URL may point at "
                       "another server")


def refuse_another_api(response: httpx.Response) -> None:
    """ApiError when an answer lacks dncq's VERSION_HEADER: another server answered (its
    JSON, of another shape, would end a command in a traceback, or be said bare). A server
    error is left to `checked`: dncq's own unexpected one (HTTP 500) carries no header."""
    if VERSION_HEADER in response.headers or response.status_code >= 500:
        return
    said = f": {response.read()[:200].decode(errors='replace').strip()}" \
        if response.is_error else ""  # a refusal's few words (a download's too)
    raise ApiError(f"{response.url} answered HTTP {response.status_code} without the "
                   f"{VERSION_HEADER} header of dncq's answers{said} (not dncq's answer: "
                   "DNCQ_URL may point at another server, or at a dncq older than this CLI)")


NO_ROUTE = "Not Found"  # dncq's statusMsg for a path it has no route for
_NO_ROUTE_HINT = ("no such path here: DNCQ_URL is dncq's address (http://host:port), "
                  "without /api")


def key_source(settings: Settings) -> str:
    """Where the key the CLI sends comes from, said with a refusal of it (or of none)."""
    if settings.api_key is not None:
        given = "DNCQ_API_KEY" if "DNCQ_API_KEY" in os.environ else "api_key of DNCQ_CONFIG_FILE"
        return f"the CLI sent the key set by {given}"
    key_file = (settings.data_dir / API_KEY_FILE).resolve()
    if key_file.exists():
        return f"the CLI sent the key in {key_file}; DNCQ_API_KEY sends another"
    return (f"the CLI sends DNCQ_API_KEY, or else the key in {key_file}, which is not there "
            "(DNCQ_DATA_DIR names the data folder `dncq serve` made it in)")


def _locked_out(said: str | None, retry_after: str | None) -> str:
    """What a 20429 says, on the local clock: `this address (10.0.0.7) is locked out for
    wrong API keys until 2026-12-08 11:15:00 CET: ...`, and how an admin ends it sooner; the
    API's own words give it in UTC."""
    found = _LOCKED_ADDRESS.search(said or "")
    address = f" ({found[1]})" if found else ""
    named = found[1] if found else "ADDRESS"
    sooner = (f"; an admin ends it sooner with `dncq lockouts end {named}` from another "
              "address, or with --local on dncq's host")
    until = _retry_at(retry_after)
    if until is None:
        return (f"this address{address} is locked out for wrong API keys: dncq refuses every "
                f"key from it for now, the right one too{sooner}")
    return (f"this address{address} is locked out for wrong API keys until "
            f"{local_text(until, seconds=True)}: dncq refuses every key from it until then, "
            f"the right one too{sooner}")


def _retry_at(retry_after: str | None) -> datetime | None:
    """When a Retry-After header of seconds, as dncq sends it, ends; None without one."""
    value = (retry_after or "").strip()
    return datetime.now(UTC) + timedelta(seconds=int(value)) if value.isdecimal() else None


def checked(response: httpx.Response, *, key_hint: str) -> Any:
    """The JSON body, or ApiError when it reports a failure or is not dncq's; `key_hint`
    follows a refusal of the key."""
    refuse_a_page(response)
    refuse_another_api(response)
    try:
        body = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict) and body.get("errorCode"):
        said = body.get("statusMsg")
        hint = key_hint if body["errorCode"] in (20401, 20403, KEYS_LOCKED_OUT) else (
            _NO_ROUTE_HINT if said == NO_ROUTE else None)  # not a role's refusal (20406)
        if body["errorCode"] == KEYS_LOCKED_OUT:
            said = _locked_out(said, response.headers.get("retry-after"))
        # One sentence: `10003 Machine ID does not exist: Invalid MachineID (1O01) (did you
        # mean 1001?)`, the errorMsg's full stop left out before what follows it.
        refusal = f"{body['errorCode']} {body.get('errorMsg') or ''}".strip()
        if why := "; ".join(part for part in (said, hint) if part):
            refusal = f"{refusal.removesuffix('.')}: {why}"
        raise ApiError(refusal, code=body["errorCode"], status_msg=said)
    if response.is_error and body is None:  # dncq's errors are JSON: another server said it
        raise ApiError(f"{response.url} answered HTTP {response.status_code}: "
                       f"{response.text[:300].strip()} (not dncq's answer: DNCQ_URL may point "
                       "at another server, or at a proxy that cannot reach dncq)")
    if response.is_error:
        raise ApiError(f"HTTP {response.status_code}: {response.text[:300]}")
    return body
