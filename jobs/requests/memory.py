"""What a machine's requests leave for the programs it sends next, until it expires.

A compare request (`(CMP=0010)`) says the next program received is compared, not stored; a
directory runner (`(RCVDIR=JOB42)`) sends the programs received after it to a folder. Kept
per machine in the data folder (shared by every worker of a fleet), written whole.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from jobs.folders import private_dir
from jobs.settings import Settings


@dataclass(frozen=True)
class Pending:
    """One thing asked for the next programs: what, its argument, until when (POSIX s)."""

    what: str  # "compare" or "directory"
    folder: str
    name: str | None
    until: float


def _file(settings: Settings, machine_id: str) -> Path:
    return private_dir(settings.data_dir / "requests") / f"{machine_id}.json"


def _load(settings: Settings, machine_id: str) -> dict[str, Pending]:
    try:
        raw = json.loads(_file(settings, machine_id).read_text())
    except (FileNotFoundError, ValueError):
        return {}
    now = time.time()
    return {k: p for k, v in raw.items() if (p := Pending(**v)).until > now}


def _save(settings: Settings, machine_id: str, items: dict[str, Pending]) -> None:
    path = _file(settings, machine_id)
    temp = path.with_suffix(f".{os.getpid()}.tmp")
    temp.write_text(json.dumps({k: asdict(v) for k, v in items.items()}))
    temp.replace(path)


def remember(settings: Settings, machine_id: str, pending: Pending) -> None:
    """Keep `pending` for the machine's next programs (one of each kind: the newest wins)."""
    items = _load(settings, machine_id)
    items[pending.what] = pending
    _save(settings, machine_id, items)


def get(settings: Settings, machine_id: str, what: str) -> Pending | None:
    """What is pending of that kind, if it has not expired."""
    return _load(settings, machine_id).get(what)


def take(settings: Settings, machine_id: str, what: str) -> Pending | None:
    """What is pending of that kind, now forgotten (a compare is for one program)."""
    items = _load(settings, machine_id)
    found = items.pop(what, None)
    if found is not None:
        _save(settings, machine_id, items)
    return found
