"""A machine's programs as today's OctoPrint lists files (`GET /api/files`).

The same files as the seed's `gcodefiles` listing (jobs.library.seed_listing), in the
shape OctoPrint 1.x answers and its clients read (octorest's `files()`, octoclient):
sizes in bytes, dates in POSIX seconds, `path`, `type` and `typePath`, `refs` (a local
file's `download` too: its library bytes). A local file's `path` is its library path
(`CAM/PART.gcode`), the one an upload answers: unique where two assigned folders hold one
name. A machine tool's program has no print analysis, so `gcodeAnalysis` is left out, as
OctoPrint leaves it out of a file not analysed yet; `prints` counts the machine's
drip-feed runs of the program.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any
from urllib.parse import quote, urlencode

from jobs.library.seed_listing import ListedFile, of_program

TYPE_PATH = ["machinecode", "gcode"]


def _seconds(when: datetime | float | None) -> int | None:
    if when is None:
        return None
    return int(when.timestamp() if isinstance(when, datetime) else when)


def prints_of(runs: dict[str, Any] | None) -> dict[str, Any] | None:
    """OctoPrint's `prints` from a program's runs (jobs.library.record.runs_by_program)."""
    if not runs:
        return None
    shown: dict[str, Any] = {"success": runs["success"], "failure": runs["failure"]}
    if runs.get("last"):
        shown["last"] = {"date": _seconds(runs["last"]["date"]),
                         "success": runs["last"]["success"]}
    return shown


@dataclass(frozen=True)
class Refs:
    """Where a listing's `refs` point."""

    resources: str  # where this listing is served: `http://dncq/machines/1010/api/files`
    downloads: str  # the library's bytes: `http://dncq/api/library/content`
    query: str = ""  # what a resource's URL needs after its path: `?machineID=1010`

    def resource(self, origin: str, path: str) -> str:
        """The URL of one file's entry: `http://dncq/machines/1010/api/files/local/CAM/P.nc`."""
        return f"{self.resources}/{origin}/{quote(path)}{self.query}"

    def download(self, folder: str, name: str) -> str:
        """The URL of a library program's bytes."""
        return f"{self.downloads}/{quote(f'{folder}/{name}')}"


def refs_at(server: str, prefix: str, machine_id: str | None = None) -> Refs:
    """The refs of a listing served at `server` under `prefix` (`/machines/1010`, or none);
    a file's keeps the unprefixed listing's `?machineID=` (a key scoped to the machine
    names it by itself)."""
    return Refs(resources=f"{server}{prefix}/api/files", downloads=f"{server}/api/library/content",
                query=f"?{urlencode({'machineID': machine_id})}" if machine_id else "")


def path_of(listed: ListedFile) -> str:
    """A file's `path`: a local one's library path, a machine's as the contract lists it."""
    return f"{listed.folder}/{listed.name}" if listed.folder is not None else listed.name


def entry(listed: ListedFile, runs: dict[str, Any] | None, refs: Refs) -> dict[str, Any]:
    """One file as OctoPrint's `files` lists it."""
    path = path_of(listed)
    shown: dict[str, Any] = {
        "name": listed.base_name, "display": listed.base_name,
        "path": path, "type": TYPE_PATH[0], "typePath": TYPE_PATH,
        "origin": listed.origin,
        "refs": {"resource": refs.resource(listed.origin, path)}}
    if listed.folder is not None:  # as OctoPrint, a download for local files alone
        shown["refs"]["download"] = refs.download(listed.folder, listed.name)
    if listed.size is not None:
        shown["size"] = listed.size
    if (date := _seconds(listed.date)) is not None:
        shown["date"] = date
    if prints := prints_of(runs):
        shown["prints"] = prints
    return shown


def listing(files: Iterable[ListedFile], runs: dict[str, dict[str, Any]], refs: Refs,
            *, free: int | None, total: int | None) -> dict[str, Any]:
    """OctoPrint's retrieve response; `free` and `total` (bytes) only when told."""
    answer: dict[str, Any] = {"files": [entry(f, of_program(runs, f), refs) for f in files]}
    if free is not None:
        answer["free"] = free
    if total is not None:
        answer["total"] = total
    return answer
