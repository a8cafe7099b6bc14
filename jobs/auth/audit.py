"""The audit trail: every state-changing request recorded once answered; read back and
exported as CSV."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Iterator
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from jobs.auth.models import AuditEvent
from jobs.auth.roles import Principal
from jobs.db import rowcount
from jobs.models import utcnow

MAX_LIMIT = 10_000
CSV_COLUMNS = ["at", "who", "kind", "role", "address", "method", "path", "status", "action",
               "target", "detail"]
_SECRET_WORDS = ("password", "secret", "token", "key", "hash")


def record(*, session: Session, principal: Principal | None, address: str | None, method: str,
           path: str, status: int, action: str, target: str | None = None,
           detail: dict[str, Any] | None = None) -> None:
    """Add one event; `principal` None: a request refused before anyone was recognised.

    `detail` keeps no value under a name that sounds secret (password, key, token...).
    """
    session.add(AuditEvent(
        who=principal.name if principal else "-",
        kind=principal.kind if principal else "none",
        role=principal.role.value if principal else None,
        address=(address or None) and address[:64], method=method.upper()[:8],
        path=_escaped(path)[:500], status=status, action=action[:64],
        target=_escaped(target)[:255] if target else None,
        detail=_without_secrets(detail) if detail else None))
    session.flush()


def _escaped(text: str) -> str:
    """`text` with what is not printable written as an escape (`\\x00`): PostgreSQL stores
    no NUL, so a request refused for one would go unrecorded, and a line end would make a
    second line of the trail's text."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _without_secrets(detail: dict[str, Any]) -> dict[str, Any]:
    return {k: ("***" if any(w in k.lower() for w in _SECRET_WORDS)
                else _escaped(v) if isinstance(v, str) else v)
            for k, v in detail.items()}


def list_events(*, session: Session, who: str | None = None, action: str | None = None,
                since: datetime | None = None, until: datetime | None = None,
                limit: int = 200, offset: int = 0) -> list[AuditEvent]:
    """Events newest first, after skipping `offset` of them (a page); `action` `jobs`
    matches `jobs.create`, `jobs.retry`..."""
    query = select(AuditEvent)
    if who is not None:
        query = query.where(AuditEvent.who == who)
    if action is not None:
        query = query.where((AuditEvent.action == action)
                            | AuditEvent.action.startswith(action + ".", autoescape=True))
    if since is not None:
        query = query.where(AuditEvent.at >= since)
    if until is not None:
        query = query.where(AuditEvent.at < until)
    limit = max(1, min(limit, MAX_LIMIT))
    return list(session.scalars(query.order_by(AuditEvent.at.desc(), AuditEvent.id.desc())
                                .limit(limit).offset(max(0, offset))))


def names_seen(*, session: Session) -> tuple[list[str], list[str]]:
    """Every principal and every action the trail holds, sorted: what a filter offers."""
    whos = session.scalars(select(AuditEvent.who).distinct().order_by(AuditEvent.who))
    actions = session.scalars(select(AuditEvent.action).distinct()
                              .order_by(AuditEvent.action))
    return list(whos), list(actions)


def prune(*, session: Session, older_than: timedelta, by: str) -> int:
    """Remove events older than `older_than`; how many. The pruning is itself an event
    (who pruned, from when), so the trail never loses history without saying so."""
    cutoff = utcnow() - older_than
    removed = rowcount(session.execute(delete(AuditEvent).where(AuditEvent.at < cutoff)))
    record_local(session=session, by=by, command="dncq audit prune", action="audit.prune",
                 detail={"removed": removed, "before": cutoff.isoformat()})
    return removed


def record_local(*, session: Session, by: str, command: str, action: str,
                 target: str | None = None, detail: dict[str, Any] | None = None) -> None:
    """Add the event of a command run on dncq's host against its database (`by`: the
    system user who ran it, `local:NAME`)."""
    session.add(AuditEvent(who=by, kind="local", role=None, address=None, method="CLI",
                           path=command, status=200, action=action, target=target,
                           detail=detail))
    session.flush()


def view(event: AuditEvent) -> dict[str, Any]:
    """An event as the API shows it."""
    return {"id": event.id, "at": event.at.isoformat(), "who": event.who, "kind": event.kind,
            "role": event.role, "address": event.address, "method": event.method,
            "path": event.path, "status": event.status, "action": event.action,
            "target": event.target, "detail": event.detail}


CSV_CHUNK_CHARS = 64 * 1024


def as_csv(events: Iterable[AuditEvent]) -> Iterator[str]:
    """The events as CSV text, a header row first, in chunks of about CSV_CHUNK_CHARS.

    Not a chunk per row: each chunk of a streamed answer is a hand-over between threads,
    and 10,000 of them made an export of 10,000 events take seconds.
    """
    buffer = io.StringIO()
    writer = csv.writer(buffer)

    def flushed() -> str:
        text = buffer.getvalue()
        buffer.seek(0)
        buffer.truncate()
        return text

    writer.writerow(CSV_COLUMNS)
    for event in events:
        shown = view(event)
        shown["detail"] = "" if event.detail is None else _flat(event.detail)
        writer.writerow([_cell(shown[c]) for c in CSV_COLUMNS])
        if buffer.tell() >= CSV_CHUNK_CHARS:
            yield flushed()
    yield flushed()


def _flat(detail: dict[str, Any]) -> str:
    return "; ".join(f"{k}={v if isinstance(v, str) else json.dumps(v)}"
                     for k, v in detail.items())


def _cell(value: Any) -> str:
    """A CSV cell a spreadsheet will not run as a formula (=, +, -, @ at its start)."""
    text = "" if value is None else str(value)
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text
