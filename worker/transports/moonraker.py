"""A machine whose files sit behind Moonraker (Klipper's API server): its `gcodes` root.

Moonraker is a file server in front of the machine (`own_storage` False). It answers
most refusals with a bare 400, so existence, emptiness and parents are checked here
before each change; the window between check and change is open to other clients.
"""

from __future__ import annotations

import contextlib
import re
import time
from collections.abc import Iterable, Iterator
from typing import Any, ClassVar, Literal
from urllib.parse import quote

import httpx
from pydantic import SecretStr

from worker.transports.base import (
    BadPath,
    Capabilities,
    Entry,
    Exists,
    NetworkOptions,
    NoMachineControl,
    NotEmpty,
    NotFound,
    ProgressFn,
    TransportError,
    byte_count,
)
from worker.transports.http import (
    ServerUrl,
    body_chunks,
    clean_path,
    http_errors,
    network_client,
    spooled_upload,
    streamed_get,
)

THUMBS = ".thumbs"  # Moonraker's thumbnails beside each G-code it analysed: not listed
MIB = 1024 * 1024
FORM_BYTES = 4096  # the upload's form around the file (root, path, its name), at most
# What an upload form's file name escapes as %22, %0A… (HTML5 form encoding, httpx's too)
_ESCAPED_IN_FORMS = re.compile(r'["\x00-\x1f]')
# A transport is opened per operation: each Moonraker's upload limit is kept this long by
# the process (its URL and key), so a raised max_upload_size is seen within a minute.
UPLOAD_LIMIT_KEPT_S = 60.0
_upload_limits: dict[tuple[str, str | None], tuple[int | None, float]] = {}
_clock = time.monotonic  # when a kept limit was read, in seconds


class MoonrakerOptions(NetworkOptions):
    """Options of a machine behind Moonraker (fleet file `options:`)."""

    url: ServerUrl
    """Base URL of Moonraker, such as `http://voron.local:7125`."""
    api_key: SecretStr | None = None
    """Moonraker's API key, sent as `X-Api-Key`; None when the worker is a trusted client."""
    root: Literal["gcodes"] = "gcodes"
    """The file root reached; `gcodes` is the one clients may write."""


class MoonrakerTransport(NoMachineControl):
    """The files of one Moonraker root over its HTTP API."""

    capabilities: ClassVar[Capabilities] = Capabilities()
    own_storage: ClassVar[bool] = False
    server_row: ClassVar[str | None] = "Moonraker"

    def __init__(self, options: MoonrakerOptions) -> None:
        self.options = options
        self.root = options.root
        headers = {"X-Api-Key": options.api_key.get_secret_value()} if options.api_key else {}
        self._client = network_client(options, base_url=str(options.url).rstrip("/") + "/",
                                      headers=headers)
        self._server_key = (str(options.url).rstrip("/"),
                            options.api_key.get_secret_value() if options.api_key else None)

    def upload_limit(self) -> int | None:
        """The most bytes Moonraker takes in one upload, body and form together (its
        `[server] max_upload_size`, in MiB); None when it does not say. Read from its
        server/config once per `UPLOAD_LIMIT_KEPT_S` by the process.

        Tornado refuses a larger body before reading it and closes the connection, which a
        client still sending sees about half the time as a reset, not as the refusal: a
        dropped link, tried again to the same end.
        """
        kept = _upload_limits.get(self._server_key)
        if kept is not None and _clock() - kept[1] < UPLOAD_LIMIT_KEPT_S:
            return kept[0]
        try:
            response = self._client.get("server/config")
        except httpx.HTTPError:
            return None  # asked again at the next upload
        try:
            mib = response.json()["result"]["config"]["server"]["max_upload_size"]
            limit = int(mib) * MIB if response.is_success else None
        except (ValueError, KeyError, TypeError):
            limit = None  # an older Moonraker, or no right to read it
        _upload_limits[self._server_key] = (limit, _clock())
        return limit

    def _rooted(self, path: str) -> str:
        return f"{self.root}/{path}" if path else self.root

    def _directory(self, path: str) -> dict[str, Any]:
        """Moonraker's listing of the folder at `path`."""
        # 400 here is "Directory does not exist" (a path outside the root is caught first)
        with http_errors(path or "/", by_status={400: NotFound}):
            response = self._client.get(
                "server/files/directory", params={"path": self._rooted(path), "extended": "false"}
            )
            response.raise_for_status()
        result: dict[str, Any] = response.json()["result"]
        return result

    def free_bytes(self) -> int | None:
        """The `disk_usage.free` Moonraker gives with a listing of its root."""
        usage = self._directory("").get("disk_usage") or {}
        return byte_count(usage.get("free"))

    def _child(self, path: str) -> dict[str, Any] | None:
        """The parent's listing record of `path` (with `is_dir`), None when there is none."""
        parent, _, name = path.rpartition("/")
        listing = self._directory(parent)
        for info in listing.get("dirs", []):  # .thumbs too: writing it must say Exists
            if info.get("dirname") == name:
                return {**info, "is_dir": True}
        for info in listing.get("files", []):
            if info.get("filename") == name:
                return {**info, "is_dir": False}
        return None

    # -- primitives --------------------------------------------------------

    def list_dir(self, path: str) -> list[Entry]:
        path = clean_path(path)
        listing = self._directory(path)
        entries = [_entry(d["dirname"], True, d) for d in _dirs(listing)]
        entries += [_entry(f["filename"], False, f) for f in listing.get("files", [])]
        return sorted(entries, key=lambda e: e.name)

    def stat(self, path: str) -> Entry:
        path = clean_path(path)
        if not path:
            return Entry("", True)
        info = self._child(path)
        if info is None:
            raise NotFound(path)
        return _entry(path.rpartition("/")[2], info["is_dir"], info)

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        path = clean_path(path)
        response = streamed_get(  # 403: a folder, not a file
            self._client, _url("server/files", self._rooted(path)),
            lambda: http_errors(path, by_status={403: NotFound}))
        total = int(response.headers["Content-Length"]) if "Content-Length" in response.headers \
            else None
        return body_chunks(response, errors=lambda: http_errors(path), total=total,
                           progress=progress)

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        """Upload a new file.

        Moonraker overwrites and creates missing folders, so both are checked first;
        a file another client stores under the name in between is overwritten.
        Moonraker receives the upload into a temporary file and moves it into place.
        """
        path = clean_path(path)
        folder, _, name = path.rpartition("/")
        if not name:
            raise BadPath(f"not a file name: {path!r}")
        if why := _renamed_by_moonraker(name):  # it would overwrite that other name
            raise BadPath(f"{path}: {why}")
        listed = _names(self._directory(folder))  # NotFound if the folder is missing
        if name in listed:
            raise Exists(path)
        with spooled_upload(chunks, progress) as (spool, size), http_errors(path):
            limit = self.upload_limit()
            if limit is not None and size + FORM_BYTES > limit:
                raise BadPath(f"{path}: {size} bytes are more than Moonraker takes in one "
                              f"upload (max_upload_size {limit // MIB} MiB, [server])")
            response = self._client.post(
                "server/files/upload",
                data={"root": self.root, "path": folder},
                files={"file": (name, spool, "application/octet-stream")},
            )
            if response.status_code == 400 and not response.content:
                # Moonraker's refusals carry JSON; a bare 400 is Tornado's, before the body
                raise BadPath(f"{path}: Moonraker refused the upload of {size} bytes unread "
                              "(HTTP 400): larger than its max_upload_size ([server], "
                              "1024 MiB unless set)")
            response.raise_for_status()
        stored = (response.json().get("item") or {}).get("path")
        if stored is not None and stored != path:  # renamed in a way not foreseen above
            if stored.rpartition("/")[2] not in listed:  # ours alone: no one else's file
                with contextlib.suppress(TransportError):
                    self.delete(stored)
            raise BadPath(f"{path}: Moonraker stores this name as {stored!r}")
        return size

    def delete(self, path: str) -> None:
        path = clean_path(path)
        with http_errors(path, by_status={400: NotFound}):  # 400: "Invalid file path"
            self._client.delete(_url("server/files", self._rooted(path))).raise_for_status()

    def make_dir(self, path: str) -> None:
        path = self._folder_path(path)
        if self._child(path) is not None:  # NotFound when the parent is missing
            raise Exists(path)
        with http_errors(path, by_status={400: Exists}):  # os.mkdir lost a race
            self._client.post(
                "server/files/directory", params={"path": self._rooted(path)}
            ).raise_for_status()

    def remove_dir(self, path: str) -> None:
        path = self._folder_path(path)
        listing = self._directory(path)
        if _dirs(listing) or listing.get("files"):
            raise NotEmpty(path)
        if len(_dirs(listing)) != len(listing.get("dirs", [])):  # thumbnails of deleted files
            with http_errors(f"{path}/{THUMBS}", by_status={400: NotFound}):
                self._client.delete(
                    "server/files/directory",
                    params={"path": self._rooted(f"{path}/{THUMBS}"), "force": "true"},
                ).raise_for_status()
        with http_errors(path, by_status={400: NotEmpty}):  # os.rmdir lost a race
            self._client.delete(
                "server/files/directory", params={"path": self._rooted(path), "force": "false"}
            ).raise_for_status()

    @staticmethod
    def _folder_path(path: str) -> str:
        path = clean_path(path)
        if not path:
            raise BadPath("the top folder cannot be made or removed")
        return path

    def close(self) -> None:
        self._client.close()


def _renamed_by_moonraker(name: str) -> str | None:
    """Why Moonraker would store an upload named `name` under another name, or None."""
    if name != name.strip():
        return "Moonraker strips the spaces around an uploaded file's name"
    if name.lower().endswith(".ufp"):
        return "Moonraker unpacks a .ufp upload into a .gcode file of the same stem"
    if _ESCAPED_IN_FORMS.search(name):
        return "Moonraker keeps the upload form's %-escape of quotes and control characters"
    return None


def _names(listing: dict[str, Any]) -> set[str]:
    """Every name in a listing, folders (`.thumbs` too) and files."""
    return ({d.get("dirname") for d in listing.get("dirs", [])}
            | {f.get("filename") for f in listing.get("files", [])}) - {None}


def _dirs(listing: dict[str, Any]) -> list[dict[str, Any]]:
    return [d for d in listing.get("dirs", []) if d.get("dirname") != THUMBS]


def _url(prefix: str, path: str) -> str:
    return f"{prefix}/{quote(path, safe='/')}"


def _entry(name: str, is_dir: bool, info: dict[str, Any]) -> Entry:
    size = info.get("size")
    modified = info.get("modified")
    return Entry(
        name=name,
        is_dir=is_dir,
        size=None if is_dir else size,  # Entry drops a size that is no byte count
        mtime=float(modified) if isinstance(modified, int | float) else None,
    )
