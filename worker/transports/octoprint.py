"""A machine whose files sit behind OctoPrint: its `/api/files` storage, `local` or `sdcard`.

OctoPrint is a file server in front of the machine (`own_storage` False). It only
accepts names with an extension it knows (gcode, gco, g by default; a plugin hooking
`octoprint.filemanager.extension_tree` adds nc and the like): others are BadPath.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator
from typing import Any, ClassVar, Literal
from urllib.parse import quote

import httpx
from pydantic import SecretStr

from worker.transports.base import (
    BadPath,
    Busy,
    Capabilities,
    Entry,
    Exists,
    NetworkOptions,
    NoMachineControl,
    NotEmpty,
    NotFound,
    ProgressFn,
    TransportError,
    Unsupported,
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


class OctoPrintOptions(NetworkOptions):
    """Options of a machine behind OctoPrint (fleet file `options:`)."""

    url: ServerUrl
    """Base URL of the OctoPrint instance, such as `http://octopi.local`."""
    api_key: SecretStr
    """A user's API key (or an application key), sent as `X-Api-Key`."""
    origin: Literal["local", "sdcard"] = "local"
    """`local`: OctoPrint's upload folder; `sdcard`: the printer's SD card (no folders)."""


class OctoPrintTransport(NoMachineControl):
    """The files of one OctoPrint origin over its REST API."""

    capabilities: ClassVar[Capabilities] = Capabilities()
    own_storage: ClassVar[bool] = False
    server_row: ClassVar[str | None] = "OctoPrint"

    def __init__(self, options: OctoPrintOptions) -> None:
        self.options = options
        self.origin = options.origin
        self._base = httpx.URL(str(options.url).rstrip("/") + "/")
        self._client = network_client(
            options, base_url=self._base,
            headers={"X-Api-Key": options.api_key.get_secret_value()})

    # -- HTTP and errors ---------------------------------------------------

    def _mapped(
        self, path: str, *, on_conflict: type[TransportError] = Exists
    ) -> contextlib.AbstractContextManager[None]:
        """OctoPrint's 409 means "exists", "not empty" or "in use": the caller says which."""
        return http_errors(path or "/", by_status={409: on_conflict})

    def _files_url(self, path: str) -> str:
        suffix = f"/{quote(path, safe='/')}" if path else ""
        return f"api/files/{self.origin}{suffix}"

    def _info(self, path: str) -> dict[str, Any]:
        """OctoPrint's record of the file or folder at `path` (the origin's top for "")."""
        with self._mapped(path):
            response = self._client.get(
                self._files_url(path), params={"recursive": "false", "force": "true"}
            )
            response.raise_for_status()
        data: dict[str, Any] = response.json()
        if not path:
            return {"type": "folder", "name": "", "children": data.get("files", [])}
        return data

    def _folder_children(self, path: str) -> list[dict[str, Any]]:
        if path and self.origin == "sdcard":
            raise NotFound(path)  # the SD card has no folders
        info = self._info(path)
        if info.get("type") != "folder":
            raise NotFound(path)
        children: list[dict[str, Any]] = info.get("children") or []
        return children

    def _require_folder(self, path: str) -> None:
        if path:
            self._folder_children(path)

    def free_bytes(self) -> int | None:
        """OctoPrint's `free` of its upload folder (the local origin); the SD card's is not told."""
        if self.origin != "local":
            return None
        with self._mapped(""):
            response = self._client.get(self._files_url(""), params={"recursive": "false"})
            response.raise_for_status()
        return byte_count(response.json().get("free"))

    # -- primitives --------------------------------------------------------

    def list_dir(self, path: str) -> list[Entry]:
        path = clean_path(path)
        return sorted((_entry(c) for c in self._folder_children(path)), key=lambda e: e.name)

    def stat(self, path: str) -> Entry:
        path = clean_path(path)
        if not path:
            return Entry("", True)
        if self.origin == "sdcard":  # no single-file resource for SD files: look in the list
            for child in self._folder_children(""):
                if child.get("path", child.get("name")) == path:
                    return _entry(child)
            raise NotFound(path)
        return _entry(self._info(path))

    def read(self, path: str, *, progress: ProgressFn | None = None) -> Iterator[bytes]:
        path = clean_path(path)
        info = self._info(path) if self.origin == "local" else {}
        if self.origin == "sdcard":
            stat = self.stat(path)  # raises NotFound
            info = {"type": "machinecode", "size": stat.size}
        if info.get("type") == "folder":
            raise NotFound(path)
        download = (info.get("refs") or {}).get("download")
        if self.origin == "sdcard" or not download:
            raise Unsupported(f"{path}: OctoPrint offers no download of {self.origin} files")
        total = byte_count(info.get("size"))
        response = streamed_get(self._client, self._same_origin(download),
                                lambda: self._mapped(path))
        return body_chunks(response, errors=lambda: self._mapped(path), total=total,
                           progress=progress)

    def write(
        self, path: str, chunks: Iterable[bytes], *, progress: ProgressFn | None = None
    ) -> int:
        """Upload a new file.

        `noOverwrite` makes OctoPrint refuse an existing name (409), but it checks after
        receiving the upload and before storing it, not atomically: a file another
        client stores under the same name in between is overwritten. The SD origin
        ignores `noOverwrite`, so it is checked here first, with a wider window.
        """
        path = clean_path(path)
        folder, _, name = path.rpartition("/")
        if not name:
            raise BadPath(f"not a file name: {path!r}")
        self._require_folder(folder)  # OctoPrint would create missing folders
        if self.origin == "sdcard" and self._exists(path):
            raise Exists(path)
        with spooled_upload(chunks, progress) as (spool, size), self._mapped(path):
            response = self._client.post(
                f"api/files/{self.origin}",
                data={"path": folder, "noOverwrite": "true"},
                files={"file": (name, spool, "application/octet-stream")},
            )
            response.raise_for_status()
        stored = (response.json().get("files") or {}).get(self.origin, {}).get("path")
        if stored is not None and stored != path:  # OctoPrint sanitized the name
            with contextlib.suppress(TransportError), self._mapped(stored):
                self._client.delete(self._files_url(stored)).raise_for_status()
            raise BadPath(f"{path}: OctoPrint stores this name as {stored!r}")
        return size

    def _exists(self, path: str) -> bool:
        try:
            self.stat(path)
        except NotFound:
            return False
        return True

    def delete(self, path: str) -> None:
        path = clean_path(path)
        if self.stat(path).is_dir:  # DELETE on a folder would remove it with all it holds
            raise NotFound(f"{path} is a folder")
        with self._mapped(path, on_conflict=Busy):  # 409: the file is being printed
            self._client.delete(self._files_url(path)).raise_for_status()

    def make_dir(self, path: str) -> None:
        path = self._folder_path(path)
        parent, _, name = path.rpartition("/")
        self._require_folder(parent)
        if self._exists(path):  # OctoPrint answers 201 for an existing folder
            raise Exists(path)
        with self._mapped(path, on_conflict=BadPath):  # 409: a name like a file type
            response = self._client.post(
                f"api/files/{self.origin}", data={"foldername": name, "path": parent}
            )
            response.raise_for_status()
        stored = (response.json().get("folder") or {}).get("path")
        if stored is not None and stored != path:
            raise BadPath(f"{path}: OctoPrint made the folder as {stored!r}")

    def remove_dir(self, path: str) -> None:
        """Remove an empty folder.

        OctoPrint deletes folders recursively, so emptiness is checked first; a file
        stored in between is deleted with the folder.
        """
        path = self._folder_path(path)
        if self._folder_children(path):
            raise NotEmpty(path)
        with self._mapped(path, on_conflict=Busy):
            self._client.delete(self._files_url(path)).raise_for_status()

    def _folder_path(self, path: str) -> str:
        if self.origin == "sdcard":
            raise Unsupported("OctoPrint's sdcard origin has no folders")
        path = clean_path(path)
        if not path:
            raise BadPath("the top folder cannot be made or removed")
        return path

    def close(self) -> None:
        self._client.close()

    def _same_origin(self, url: str) -> httpx.URL:
        """The download URL on the configured host, so the key never goes anywhere else."""
        target = self._base.join(url)
        if (target.scheme, target.host, target.port) == (
            self._base.scheme, self._base.host, self._base.port
        ):
            return target
        return self._base.join(target.raw_path.decode("ascii").lstrip("/"))


def _entry(info: dict[str, Any]) -> Entry:
    is_dir = info.get("type") == "folder"
    size = info.get("size")
    date = info.get("date")
    return Entry(
        name=str(info.get("name", "")),
        is_dir=is_dir,
        size=None if is_dir else size,  # Entry drops a size that is no byte count
        mtime=float(date) if isinstance(date, int | float) else None,
    )
