"""A machine's programs in the shape of OctoPrint's file listing (seed 002).

dncq stands in front of a machine as OctoPrint stands in front of a printer: its own
store is the `local` origin (the library's programs for the machine), the machine's
storage is `sdcard`. Each file carries the seed's fields; what the machine does not tell is
the seed's `n/a` and `0`.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from jobs.errors import ContractError
from jobs.fleet.door import open_files
from jobs.fleet.registry import MachineSpec
from jobs.library import analyses, record, service
from jobs.settings import Settings

log = logging.getLogger(__name__)

ORIGINS = ("local", "sdcard")
NOT_TOLD = "n/a"


def formatted_size(num_bytes: float) -> str:
    """A size as OctoPrint writes it: `1.4MB`, `3.2GB` (powers of 1024, one decimal)."""
    for unit in ("B", "KB", "MB", "GB"):
        if num_bytes < 1024:
            return f"{num_bytes:3.1f}{unit}"
        num_bytes /= 1024
    return f"{num_bytes:3.1f}TB"


def formatted_date(when: datetime | float | None) -> str:
    """A date as the seed writes it, `YYYY-MM-DD HH:mm`, in the server's local time."""
    if when is None:
        return NOT_TOLD
    if isinstance(when, int | float):
        when = datetime.fromtimestamp(when, UTC)
    return when.astimezone().strftime("%Y-%m-%d %H:%M")


@dataclass(frozen=True)
class ListedFile:
    """One file of either origin, before it is written in the seed's shape."""

    name: str
    origin: str
    size: int | None = None
    date: datetime | float | None = None
    analysis: dict[str, str] | None = None  # estimatedPrintTime, filament
    folder: str | None = None  # a local file's library folder
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def base_name(self) -> str:
        """The name without its folders (`USER/10` is `10`)."""
        return self.name.rsplit("/", 1)[-1]


def seed_entry(listed: ListedFile, prints: dict[str, Any] | None) -> dict[str, Any]:
    """One entry of `files` as the seed gives it."""
    entry: dict[str, Any] = {
        "name": listed.name,
        "bytes": listed.size if listed.size is not None else 0,
        "size": formatted_size(listed.size) if listed.size is not None else NOT_TOLD,
        "date": formatted_date(listed.date),
        "origin": listed.origin,
    }
    if listed.analysis:
        entry["gcodeAnalysis"] = listed.analysis
    if prints:
        entry["prints"] = prints
    entry.update(listed.extra)
    return entry


def prints_by_program(*, session: Session, machine_id: str) -> dict[str, dict[str, Any]]:
    """The seed's `prints` per program name from the machine's drip-feed runs.

    A run stopped on request counts as a failure, as OctoPrint counts a cancelled print;
    a run cancelled before it started never ran and is not counted.
    """
    return {name: {"failure": ran["failure"], "success": ran["success"],
                   "last": {"date": formatted_date(ran["last"]["date"]),
                            "success": ran["last"]["success"]}}
            for name, ran in record.runs_by_program(session=session,
                                                     machine_id=machine_id).items()}


def sdcard_files(spec: MachineSpec, *, data_dir: Path) -> tuple[list[ListedFile], int | None]:
    """The machine's own files below its default root, named as the contract lists them,
    and its free bytes (None where its transport does not tell)."""
    with open_files(spec, data_dir=data_dir) as files:
        start = files.paths.resolve(None, None)
        found = [ListedFile(name="/".join((*walked.parts,
                                           files.paths.listed_name(walked.entry.name))),
                            origin="sdcard", size=walked.entry.size, date=walked.entry.mtime)
                 for walked in files.walk(start)]
        free = files.free_bytes()
    return found, free


def told_size(num_bytes: int | None) -> str:
    """A size as the seed writes it, `n/a` when it is not known."""
    return formatted_size(num_bytes) if num_bytes is not None else NOT_TOLD


def local_files(*, session: Session, settings: Settings, spec: MachineSpec
                ) -> list[ListedFile]:
    """The library's programs for the machine: the approved versions of its folders."""
    return [ListedFile(name=program.name, origin="local", folder=program.folder,
                       size=version.size, date=version.created_at,
                       analysis=seed_analysis(settings, version.sha256))
            for program, version in service.machine_programs(session=session,
                                                              machine_id=spec.id)]


def seed_analysis(settings: Settings, sha256: str) -> dict[str, str] | None:
    """The seed's `gcodeAnalysis` of a stored program (analysed once per content); None,
    as OctoPrint lists a file not analysed, when its content is gone from the store: the
    rest of the listing stands, and the file's download or send says 158."""
    try:
        return analyses.seed_view(analyses.of_blob(settings, sha256))
    except ContractError as exc:
        log.warning("library content %s listed without its analysis: %s", sha256, exc)
        return None


def local_free(data_dir: Path) -> str:
    """Free space of dncq's own store (the seed's `free` for the `local` origin)."""
    return formatted_size(shutil.disk_usage(data_dir).free)


def of_program(by_program: dict[str, dict[str, Any]], listed: ListedFile) -> Any:
    """What `by_program` (runs or prints, keyed by the run's program name) holds for a
    listed file: by its name without folders, else by its whole name."""
    return by_program.get(listed.base_name) or by_program.get(listed.name)


def listing(files: Iterable[ListedFile], prints: dict[str, dict[str, Any]],
            free: str) -> dict[str, Any]:
    """The seed's retrieve response."""
    return {"files": [seed_entry(f, of_program(prints, f)) for f in files], "free": free}
