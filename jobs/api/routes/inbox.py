"""The inbox: programs machines sent that were not requests; list, show, content, diff
against the library's approved copy, approve into the library, reject, prune."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Body, Path, Query
from fastapi.responses import PlainTextResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from jobs.api.deps import RecordedBy, SessionDep, SettingsDep, requires
from jobs.api.errors import CodedHTTPError, library_errors, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.fleet import registry
from jobs.inbox import service
from jobs.inbox.models import InboxItem, InboxState
from jobs.inbox.views import item_view
from jobs.library import blobs
from jobs.library.views import program_view, version_view

router = APIRouter(prefix="/api/inbox", tags=["inbox"], route_class=CheckedRoute)

ItemId = Annotated[int, Path(ge=1, le=2**31 - 1, description="An inbox item's id")]
By = RecordedBy  # who, as the audit trail knows them


@contextlib.contextmanager
def _errors() -> Iterator[None]:
    """The library's statuses (404 missing, 400 a bad folder or name, 413 too large), and
    409 for a decision the item's state does not allow."""
    with library_errors():
        try:
            yield
        except service.Undecidable as exc:
            raise CodedHTTPError(409, exc.code, exc.status_msg) from None


class ApproveRequest(BaseModel):
    """Where the program goes in the library (default: where it was meant for), and why."""

    model_config = ConfigDict(extra="forbid")

    folder: str | None = Field(default=None, max_length=500,
                               description="Library folder; default: the item's")
    name: str | None = Field(default=None, max_length=255,
                             description="Program name; default: the item's")
    note: str = Field(default="", max_length=1000,
                      description="The version's note; default: the program's comment")


class RejectRequest(BaseModel):
    """Why the program is refused."""

    model_config = ConfigDict(extra="forbid")

    reason: str = Field(default="", max_length=1000)


@router.get("", summary="Received programs, newest first",
            dependencies=[requires(Role.VIEWER)])
def list_items(
        session: SessionDep,
        machine: Annotated[str | None, Query(max_length=64,
                                             description="Only this machine's")] = None,
        state: Annotated[InboxState | None, Query(description="Only in this state")] = None,
        limit: Annotated[int, Query(ge=1, le=service.MAX_LIST)] = 100,
) -> list[dict[str, Any]]:
    found = service.list_items(session=session, machine_id=machine, state=state, limit=limit)
    with resource_errors():  # a mistyped machine: 10003, not an empty list
        registry.check_machine_filter(session=session, machine_id=machine,
                                      held_by=InboxItem.machine_id, found=found)
    return [item_view(i) for i in found]


@router.get("/{item_id}", summary="A received program and the library's approved copy",
            dependencies=[requires(Role.VIEWER)])
def show_item(session: SessionDep, item_id: ItemId) -> dict[str, Any]:
    with _errors():
        item = service.get(session=session, item_id=item_id)
    body = item_view(item)
    copy = service.approved_copy(session=session, item=item)
    body["approved"] = version_view(copy) if copy is not None else None
    return body


@router.get("/{item_id}/content", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}},
                             "description": "The bytes as they were received"}},
            summary="The bytes as they were received",
            dependencies=[requires(Role.VIEWER)])
def item_content(session: SessionDep, settings: SettingsDep, item_id: ItemId) -> Response:
    with _errors():
        item = service.get(session=session, item_id=item_id)
        data = blobs.read_all(settings, item.sha256)  # programs of a few MB: whole
    return Response(data, media_type="application/octet-stream")


@router.get("/{item_id}/diff", response_class=PlainTextResponse,
            summary="A unified diff from the library's approved copy to the received program",
            dependencies=[requires(Role.VIEWER)])
def item_diff(session: SessionDep, settings: SettingsDep, item_id: ItemId,
              context: Annotated[int, Query(ge=0, le=1000)] = 3) -> PlainTextResponse:
    with _errors():
        text = service.diff(session=session, settings=settings, item_id=item_id,
                            context_lines=context)
    return PlainTextResponse(text)


@router.post("/{item_id}/approve",
             summary="Make it a new approved version in the library (the previous kept)",
             dependencies=[requires(Role.PROGRAMMER, action="inbox.approve")])
def approve_item(session: SessionDep, settings: SettingsDep, item_id: ItemId,
                 request: Annotated[ApproveRequest | None, Body()] = None,
                 by: By = "api") -> dict[str, Any]:
    asked = request or ApproveRequest()
    with _errors():
        made = service.approve(session=session, settings=settings, item_id=item_id,
                               folder=asked.folder, name=asked.name, decided_by=by,
                               note=asked.note)
        item = service.get(session=session, item_id=item_id)
    return {"item": item_view(item), "version": version_view(made),
            "program": program_view(made.program)}


@router.post("/{item_id}/reject", summary="Refuse it (kept until pruned)",
             dependencies=[requires(Role.PROGRAMMER, action="inbox.reject")])
def reject_item(session: SessionDep, item_id: ItemId,
                request: Annotated[RejectRequest | None, Body()] = None,
                by: By = "api") -> dict[str, Any]:
    asked = request or RejectRequest()
    with _errors():
        item = service.reject(session=session, item_id=item_id, decided_by=by,
                              reason=asked.reason)
    return {"item": item_view(item)}


@router.post("/prune", summary="Remove programs rejected longer ago than the retention",
             dependencies=[requires(Role.PROGRAMMER, action="inbox.prune")])
def prune(session: SessionDep, settings: SettingsDep) -> dict[str, Any]:
    return {"pruned": service.prune(session=session, settings=settings),
            "keepDays": settings.inbox_rejected_keep_days}
