"""A machine reached through another gateway that speaks the contract's `/api/cnc/...` API.

A storage path "a/b" is the remote machine's folder given as the relative `dirAtCNC`
"a/b" (below the remote machine's default root; "" sends no `dirAtCNC`). Large files
move through the streaming endpoints; the API key travels only in `X-Api-Key`.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterable, Iterator
from typing import Any, ClassVar

import httpx
from pydantic import Field, SecretStr, field_validator

from worker.transports.base import (
    CHUNK_BYTES,
    BadPath,
    Busy,
    Capabilities,
    ConnectFailed,
    Entry,
    Exists,
    NetworkOptions,
    NoMachineControl,
    NotEmpty,
    NotFound,
    Offline,
    Permanent,
    PermissionDenied,
    ProgressFn,
    TimedOut,
    Transient,
    TransportError,
    Unsupported,
)
from worker.transports.http import http_errors, network_client

API = "api/cnc/"  # below the base URL, which may carry a prefix of its own
UNKNOWN_MACHINE = 10003  # the contract's "Machine ID does not exist."

# The remote's `errorCode`s (jobs/errors.py of a dncq, the contract's own for 142/158/10003).
_BY_CODE: dict[int, type[TransportError]] = {
    158: NotFound,
    142: Exists,
    20009: NotEmpty,
    20003: Unsupported,
    20010: PermissionDenied,
    20008: PermissionDenied,  # the file is the running program; the remote keeps it
    20401: PermissionDenied,
    20403: PermissionDenied,
    20001: BadPath,
    20002: BadPath,  # outside the remote machine's roots
    20004: Offline,
    20011: Offline,  # disabled on the remote: marked offline there
    20005: TimedOut,
    20006: ConnectFailed,
    20007: Busy,
    # 10003: a wrong machine_id in our options; asking again will not help.
    UNKNOWN_MACHINE: Permanent,
}

# HTTP statuses whose body does not say more than the status itself.
_BY_STATUS: dict[int, type[TransportError]] = {
    401: PermissionDenied,
    403: PermissionDenied,
    408: TimedOut,
    429: Busy,
    502: ConnectFailed,
    503: Busy,
    504: TimedOut,
}


class GatewayOptions(NetworkOptions):
    """Options of a machine behind another gateway (fleet file `options:`)."""

    url: str
    """Base URL of the gateway, e.g. `https://gw.example:8080` (the API is below it)."""
    machine_id: str = Field(min_length=1)
    """The machine's ID on that gateway."""
    api_key: SecretStr | None = None
    """The gateway's API key; sent in the `X-Api-Key` header only."""
    verify_tls: bool = True
    """Check the gateway's TLS certificate (https only)."""

    @field_validator("url")
    @classmethod
    def _http_url(cls, value: str) -> str:
        try:
            url = httpx.URL(value)
        except httpx.InvalidURL as exc:
            raise ValueError(f"not a URL: {exc}") from None
        if url.scheme not in ("http", "https") or not url.host:
            raise ValueError("url must be an http:// or https:// URL with a host")
        if url.userinfo:
            raise ValueError("url must not carry credentials; give the key as api_key")
        if url.query or url.fragment:  # `?apikey=` too, which would be shown as the url is
            raise ValueError("url must not carry a query or fragment; give the key as api_key")
        return value


class GatewayTransport(NoMachineControl):
    """The storage of one machine on another gateway, through its HTTP API."""

    capabilities: ClassVar[Capabilities] = Capabilities()
    own_storage: ClassVar[bool] = False
    server_row: ClassVar[str | None] = "Gateway file server"

    def __init__(self, options: GatewayOptions) -> None:
        self.options = options
        key = options.api_key.get_secret_value() if options.api_key else ""
        self._key = key
        headers = {"X-Api-Key": key} if key else {}
        self._client = network_client(options, base_url=options.url, headers=headers,
                                      verify=options.verify_tls)

    # -- the edge: HTTP answers and httpx failures to the error tree ------------------------

    def _clean(self, text: str) -> str:
        """`text` with the API key blanked, should the far side ever echo it."""
        if not self._key:
            return text
        return re.sub(re.escape(self._key), "***", text, flags=re.IGNORECASE)

    def _mapped(self, what: str) -> contextlib.AbstractContextManager[None]:
        """Turn httpx failures into the transport's errors, once, here."""
        return http_errors(f"{what} via gateway {self.options.url}", clean=self._clean)

    def _check(self, response: httpx.Response, what: str) -> dict[str, Any]:
        """The JSON body of a successful answer; anything else raised as the matching error."""
        status = response.status_code
        where = f"{what} via gateway {self.options.url}"
        if status == 404:
            # A dncq answers unknown routes 404 with code 158: not a missing file here.
            raise Permanent(f"{where}: no gateway API at this URL (HTTP 404)")
        try:
            parsed = response.json()
        except ValueError:
            parsed = None
        body: dict[str, Any] = parsed if isinstance(parsed, dict) else {}
        code = _code(body)
        if status == 200 and isinstance(parsed, dict) and not code:
            return body
        if status in _BY_STATUS:
            cls = _BY_STATUS[status]
        elif status in (200, 400) and code:
            cls = _BY_CODE.get(code, Permanent)
        elif status >= 500:
            cls = Permanent if status == 500 else Transient
        else:
            cls = Permanent
        if code == UNKNOWN_MACHINE:
            detail = f"the gateway has no machine {self.options.machine_id!r} (10003)"
        elif code:
            detail = f"{code} {body.get('errorMsg') or ''} {body.get('statusMsg') or ''}".strip()
        else:
            detail = f"HTTP {status}, not a gateway answer"
        raise cls(self._clean(f"{where}: {detail}"))

    def _get(self, endpoint: str, what: str, **params: str) -> dict[str, Any]:
        with self._mapped(what):
            response = self._client.get(API + endpoint, params=self._params(**params))
        return self._check(response, what)

    def _params(self, **params: str) -> dict[str, str]:
        return {"machineID": self.options.machine_id, **{k: v for k, v in params.items() if v}}

    # -- primitives ---------------------------------------------------------------------------

    def list_dir(self, path: str) -> list[Entry]:
        folder = _folder(path)
        body = self._get("readProgramList", f"list {folder!r}", dirAtCNC=folder)
        entries = [Entry(str(n), False) for n in body.get("programs") or []]
        entries += [Entry(str(n), True) for n in body.get("subDirs") or []]
        return sorted(entries, key=lambda e: e.name)

    def stat(self, path: str) -> Entry:
        folder, name = _split(path)
        if not name:
            self.list_dir("")  # the top: there when the gateway can list it
            return Entry("", True)
        for entry in self.list_dir(folder):
            if entry.name == name:
                return entry
        raise NotFound(path)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        folder, name = _split(path)
        what = f"read {path!r}"
        params = self._params(fileName=name, dirAtCNC=folder)
        with self._mapped(what), self._client.stream(
                "GET", API + "receiveFileStream", params=params) as response:
            if response.status_code != 200 or not response.headers.get(
                    "content-type", "").startswith("application/octet-stream"):
                response.read()
                self._check(response, what)
                raise Permanent(f"{what} via gateway {self.options.url}: not a file stream")
            length = response.headers.get("content-length")
            total = int(length) if length and length.isdigit() else None
            done = 0
            for chunk in response.iter_bytes(CHUNK_BYTES):
                done += len(chunk)
                yield chunk
                if progress:
                    progress(done, total)

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        folder, name = _split(path)
        if not name:
            raise BadPath("cannot write the top folder")
        done = 0

        def body() -> Iterator[bytes]:
            nonlocal done
            for chunk in chunks:
                if not chunk:
                    continue  # an empty chunk would end a chunked body early
                done += len(chunk)
                yield chunk
                if progress:
                    progress(done, None)

        what = f"write {path!r}"
        # The remote spools the whole body before storing it: a failed upload leaves nothing.
        with self._mapped(what):
            response = self._client.post(API + "sendFileStream",
                                         params=self._params(fileName=name, dirAtCNC=folder),
                                         content=body())
        self._check(response, what)
        return done

    def delete(self, path: str) -> None:
        folder, name = _split(path)
        if not name:
            raise BadPath("cannot delete the top folder")
        # No force: the remote keeps refusing to delete its running program (20008).
        self._get("deleteFile", f"delete {path!r}", fileName=name, dirAtCNC=folder)

    def make_dir(self, path: str) -> None:
        folder, name = _split(path)
        if not name:
            raise Exists("the top folder is always there")
        self._get("createDir", f"make folder {path!r}", dirName=name, dirAtCNC=folder)

    def remove_dir(self, path: str) -> None:
        folder, name = _split(path)
        if not name:
            raise BadPath("cannot remove the top folder")
        self._get("deleteDir", f"remove folder {path!r}", dirName=name, dirAtCNC=folder)

    def close(self) -> None:
        self._client.close()


def _code(body: dict[str, Any]) -> int:
    """The body's non-zero `errorCode`, or 0 when there is none."""
    try:
        return int(body.get("errorCode") or 0)
    except (TypeError, ValueError):
        return 0


def _folder(path: str) -> str:
    """A storage path as the remote's relative `dirAtCNC` ("" for the top)."""
    parts = [p for p in path.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise BadPath(f"'..' is not allowed in a path: {path!r}")
    return "/".join(parts)


def _split(path: str) -> tuple[str, str]:
    """(folder, name) of a storage path; name is "" for the top."""
    folder, _, name = _folder(path).rpartition("/")
    return folder, name
