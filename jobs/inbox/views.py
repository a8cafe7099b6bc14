"""The inbox as the API shows it: items as JSON-ready dicts."""

from __future__ import annotations

from typing import Any

from jobs.inbox.models import InboxItem


def item_view(item: InboxItem) -> dict[str, Any]:
    """One item: where and when it came from, what it calls itself, its content and review."""
    return {"id": item.id, "machineID": item.machine_id, "receivedAt": item.received_at,
            "name": item.name, "folder": item.folder, "path": item.path,
            "programNumber": item.program_number, "comment": item.comment,
            "sha256": item.sha256, "size": item.size, "state": item.state.value,
            "reason": item.reason, "jobID": item.job_id, "decidedBy": item.decided_by,
            "decidedAt": item.decided_at, "libraryVersion": item.library_version}
