"""The library as the API shows it: programs and versions as JSON-ready dicts."""

from __future__ import annotations

from typing import Any

from jobs.library.models import LibraryAssignment, LibraryProgram, LibraryVersion
from jobs.library.service import approved, current


def version_view(v: LibraryVersion) -> dict[str, Any]:
    """One version: number, content id, size, state, who added it and why, the decision."""
    return {"version": v.number, "sha256": v.sha256, "size": v.size, "state": v.state.value,
            "note": v.note, "source": v.source, "createdBy": v.created_by,
            "createdAt": v.created_at, "decidedBy": v.decided_by, "decidedAt": v.decided_at}


def program_view(p: LibraryProgram, *, versions: bool = False) -> dict[str, Any]:
    """One program: where it is, its current and current approved versions."""
    latest, good = current(p), approved(p)
    body: dict[str, Any] = {
        "path": p.path, "folder": p.folder, "name": p.name, "deleted": p.deleted,
        "deletedAt": p.deleted_at, "createdAt": p.created_at,
        "current": version_view(latest) if latest else None,
        "approved": version_view(good) if good else None,
    }
    if versions:
        body["versions"] = [version_view(v) for v in reversed(p.versions)]
    return body


def reference(v: LibraryVersion) -> dict[str, Any]:
    """What a job says it sent: the program's path, the version number and its content id."""
    return {"path": v.program.path, "version": v.number, "sha256": v.sha256,
            "state": v.state.value}


def assignment_view(a: LibraryAssignment) -> dict[str, Any]:
    """One machine ↔ folder assignment."""
    return {"machineID": a.machine_id, "folder": a.folder, "createdAt": a.created_at}
