"""The audit trail (admin): `/api/audit` as JSON, `/api/audit.csv` as a CSV file."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import StreamingResponse

from jobs.api.deps import SessionDep, requires
from jobs.api.text import CheckedRoute
from jobs.auth import audit
from jobs.auth.roles import Role

router = APIRouter(tags=["audit"], route_class=CheckedRoute)

Who = Annotated[str | None, Query(max_length=100, description=(
    "Only this principal: a user's name, `key:NAME`, `admin-key`, `anonymous`"))]
Action = Annotated[str | None, Query(max_length=64, description=(
    "Only this action (`machines.put`) or group of actions (`machines`)"))]
Since = Annotated[datetime | None, Query(description="At or after this time")]
Until = Annotated[datetime | None, Query(description="Before this time")]
Limit = Annotated[int, Query(ge=1, le=audit.MAX_LIMIT)]


@router.get("/api/audit", summary="Who changed what, when, from where: newest first",
            dependencies=[requires(Role.ADMIN)])
def list_events(session: SessionDep, who: Who = None, action: Action = None,
                since: Since = None, until: Until = None,
                limit: Limit = 200) -> list[dict[str, Any]]:
    found = audit.list_events(session=session, who=who, action=action, since=since,
                              until=until, limit=limit)
    return [audit.view(e) for e in found]


@router.get("/api/audit.csv", summary="The audit trail as CSV, newest first",
            response_class=StreamingResponse,
            responses={200: {"content": {"text/csv": {}}}},
            dependencies=[requires(Role.ADMIN)])
def export_events(session: SessionDep, who: Who = None, action: Action = None,
                  since: Since = None, until: Until = None,
                  limit: Limit = audit.MAX_LIMIT) -> StreamingResponse:
    found = audit.list_events(session=session, who=who, action=action, since=since,
                              until=until, limit=limit)
    return StreamingResponse(audit.as_csv(found), media_type="text/csv; charset=utf-8",
                             headers={"Content-Disposition":
                                      'attachment; filename="dncq-audit.csv"'})
