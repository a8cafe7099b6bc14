"""A machine's programs as today's OctoPrint lists files (`GET /api/files`).

The same files as the seed's `gcodefiles` listing (jobs.library.seed_listing), in the
shape OctoPrint 1.x answers and its clients read (octorest's `files()`, octoclient):
sizes in bytes, dates in POSIX seconds, `path`, `type` and `typePath`, `refs` (a local
file's `download` too: its library bytes). A machine tool's program has no print analysis,
so `gcodeAnalysis` is left out, as OctoPrint leaves it out of a file not analysed yet;
`prints` counts the machine's drip-feed runs of the program.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any
from urllib.parse import quote

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


def entry(listed: ListedFile, runs: dict[str, Any] | None, refs: Refs) -> dict[str, Any]:
    """One file as OctoPrint's `files` lists it."""
    shown: dict[str, Any] = {
        "name": listed.base_name, "display": listed.base_name,
        "path": listed.name, "type": TYPE_PATH[0], "typePath": TYPE_PATH,
        "origin": listed.origin,
        "refs": {"resource":
                 f"{refs.resources}/{listed.origin}/{quote(listed.name)}{refs.query}"}}
    if listed.folder is not None:  # as OctoPrint, a download for local files alone
        shown["refs"]["download"] = f"{refs.downloads}/{quote(f'{listed.folder}/{listed.name}')}"
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
