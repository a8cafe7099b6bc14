"""The program library: add versions (the raw body), list, show, history, diff, restore,
delete, approve, reject, and which folders each machine takes."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import PlainTextResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict
from starlette.concurrency import run_in_threadpool

from jobs.api.deps import RecordedBy, SessionDep, SettingsDep, requires
from jobs.api.errors import CodedHTTPError, cut_short, library_errors, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.fleet import registry
from jobs.library import analyses, blobs, names, record, service
from jobs.library.models import LibraryAssignment, VersionState
from jobs.library.views import assignment_view, program_view, version_view

router = APIRouter(prefix="/api/library", tags=["library"], route_class=CheckedRoute)

PROGRAMS_PATH = "/api/library/programs"  # the upload: a raw body of any size

By = RecordedBy  # who, as the audit trail knows them
VERSION_MAX = 2**31 - 1  # versions are an INTEGER column: a larger number is none of them
Number = Annotated[int, Query(ge=1, le=VERSION_MAX, description="A version number")]
MaybeNumber = Annotated[int | None, Query(ge=1, le=VERSION_MAX)]


def _split(path: str) -> tuple[str, str]:
    with library_errors():
        return names.split(path)


@router.post(
    "/programs", status_code=201,
    summary="Add a program, or a new version of one (the raw body, any size)",
    openapi_extra={"requestBody": {"content": {"application/octet-stream": {}},
                                   "required": True}},
    dependencies=[requires(Role.PROGRAMMER, action="library.add")],
)
async def add_program(
        request: Request, session: SessionDep, settings: SettingsDep,
        folder: Annotated[str, Query(description="Library folder: VIPROS, VIPROS/OLD")],
        name: Annotated[str, Query(description="The program's name in its folder")],
        note: Annotated[str, Query(max_length=1000, description="Why this version")] = "",
        approve: Annotated[bool, Query(description="Approve the version at once")] = False,
        by: By = "api") -> dict[str, Any]:
    with library_errors():  # refused before a byte is stored
        names.check_folder(folder)
        names.check_program_name(name)

    def check_size(size_bytes: int) -> None:  # an empty one: before it is kept
        with library_errors():
            service.check_size(folder=folder, name=name, size_bytes=size_bytes)

    blob = await blobs.put_stream(settings, request.stream(), check=check_size)

    def record() -> dict[str, Any]:
        with library_errors():
            added = service.add(session=session, folder=folder, name=name, blob=blob,
                                note=note, created_by=by, approve=approve)
        return {"added": added.created, "restored": added.restored,
                "version": version_view(added.version),
                "program": program_view(added.version.program)}

    return await run_in_threadpool(record)


@router.get("/programs", summary="Library programs by folder and name",
            dependencies=[requires(Role.VIEWER)])
def list_programs(
        session: SessionDep,
        folder: Annotated[str | None, Query(description="Only this folder and those below")]
        = None,
        deleted: Annotated[bool, Query(description="Include deleted programs")] = False,
) -> list[dict[str, Any]]:
    with library_errors():
        found = service.list_programs(session=session, folder=folder, deleted=deleted)
    return [program_view(p) for p in found]


@router.get("/programs/{path:path}", summary="A program and its versions, newest first",
            dependencies=[requires(Role.VIEWER)])
def show_program(session: SessionDep, settings: SettingsDep, path: str) -> dict[str, Any]:
    folder, name = _split(path)
    with library_errors():
        program = service.find(session=session, folder=folder, name=name, deleted=True)
    body = program_view(program, versions=True)
    shown = service.approved(program) or service.current(program)
    if shown is not None:  # of the version rollouts use: analysed once per content
        with library_errors():
            body["analysis"] = analyses.view(analyses.of_blob(settings, shown.sha256))
    body["runs"] = record.runs_by_machine(session=session, name=name)
    body["sends"] = record.sends_by_machine(session=session, program=program)
    return body


@router.delete("/programs/{path:path}", summary="Delete a program (its history is kept)",
               dependencies=[requires(Role.PROGRAMMER, action="library.delete")])
def delete_program(session: SessionDep, path: str) -> dict[str, Any]:
    folder, name = _split(path)
    with library_errors():
        return program_view(service.delete(session=session, folder=folder, name=name))


@router.get("/history/{path:path}", summary="Every version of a program, newest first",
            dependencies=[requires(Role.VIEWER)])
def program_history(session: SessionDep, path: str) -> list[dict[str, Any]]:
    folder, name = _split(path)
    with library_errors():
        return [version_view(v) for v in service.history(session=session, folder=folder,
                                                         name=name)]


@router.get("/diff/{path:path}", response_class=PlainTextResponse,
            summary="A unified diff between two versions of a program",
            dependencies=[requires(Role.VIEWER)])
def diff_versions(session: SessionDep, settings: SettingsDep, path: str,
                  old: Number, new: Number,
                  context: Annotated[int, Query(ge=0, le=1000)] = 3) -> PlainTextResponse:
    folder, name = _split(path)
    with library_errors():
        text = service.diff(session=session, settings=settings, folder=folder, name=name,
                            old=old, new=new, context_lines=context)
    return PlainTextResponse(text)


@router.get("/content/{path:path}", response_class=StreamingResponse,
            summary="A version's bytes (default: the current approved version)",
            dependencies=[requires(Role.VIEWER)])
def version_content(session: SessionDep, settings: SettingsDep, path: str,
                    version: MaybeNumber = None) -> StreamingResponse:
    folder, name = _split(path)
    with library_errors():
        chosen = service.for_send(session=session, folder=folder, name=name, number=version)
        chunks = blobs.read(settings, chosen.sha256)
        first = next(chunks, b"")  # a missing blob is an error before the headers go out
    return StreamingResponse(
        cut_short(_chained(first, chunks), f"library content {path} v{chosen.number}"),
        media_type="application/octet-stream",
        headers={"X-Library-Version": str(chosen.number)})


def _chained(first: bytes, rest: Iterator[bytes]) -> Iterator[bytes]:
    yield first
    yield from rest


@router.post("/restore/{path:path}", status_code=201,
             summary="A new version with the bytes of an old one (note: restore of vN)",
             dependencies=[requires(Role.PROGRAMMER, action="library.restore")])
def restore_version(session: SessionDep, path: str, version: Number,
                    approve: bool = False, by: By = "api") -> dict[str, Any]:
    folder, name = _split(path)
    with library_errors():
        added = service.restore(session=session, folder=folder, name=name, number=version,
                                created_by=by, approve=approve)
    return {"added": added.created, "restored": added.restored,
            "version": version_view(added.version), "program": program_view(added.version.program)}


@router.post("/approve/{path:path}", summary="Approve a version (default: the current one)",
             dependencies=[requires(Role.PROGRAMMER, action="library.approve")])
def approve_version(session: SessionDep, path: str,
                    version: MaybeNumber = None,
                    by: By = "api") -> dict[str, Any]:
    return _decide(session, path, version, VersionState.APPROVED, by)


@router.post("/reject/{path:path}", summary="Reject a version",
             dependencies=[requires(Role.PROGRAMMER, action="library.reject")])
def reject_version(session: SessionDep, path: str, version: Number,
                   by: By = "api") -> dict[str, Any]:
    return _decide(session, path, version, VersionState.REJECTED, by)


def _decide(session: SessionDep, path: str, number: int | None, state: VersionState,
            by: str) -> dict[str, Any]:
    folder, name = _split(path)
    with library_errors():
        try:
            chosen = service.decide(session=session, folder=folder, name=name, number=number,
                                    state=state, decided_by=by)
        except service.DecidedMeanwhile as exc:  # as the inbox answers a decision that met
            raise CodedHTTPError(409, exc.code, exc.status_msg) from None
    return {"version": version_view(chosen), "program": program_view(chosen.program)}


class AssignmentRequest(BaseModel):
    """Machines to give (or take) a library folder."""

    model_config = ConfigDict(extra="forbid")

    folder: str
    machines: list[str]


@router.get("/assignments", summary="Which library folders each machine takes",
            dependencies=[requires(Role.VIEWER)])
def list_assignments(session: SessionDep, machine: str | None = None,
                     folder: str | None = None) -> list[dict[str, Any]]:
    found = service.assignments(session=session, machine_id=machine, folder=folder)
    with resource_errors():  # a mistyped machine: 10003, not an empty list
        registry.check_machine_filter(session=session, machine_id=machine,
                                      held_by=LibraryAssignment.machine_id, found=found)
    return [assignment_view(a) for a in found]


@router.post("/assignments", summary="Give machines the programs of a library folder",
             dependencies=[requires(Role.PROGRAMMER, action="library.assign")])
def assign_folder(session: SessionDep, request: AssignmentRequest) -> list[dict[str, Any]]:
    with library_errors():
        return [assignment_view(a) for a in service.assign(
            session=session, folder=request.folder, machine_ids=request.machines)]


@router.post("/assignments/remove", summary="Take a library folder from machines",
             dependencies=[requires(Role.PROGRAMMER, action="library.unassign")])
def unassign_folder(session: SessionDep, request: AssignmentRequest) -> dict[str, Any]:
    with library_errors():
        n = service.unassign(session=session, folder=request.folder,
                             machine_ids=request.machines)
    return {"folder": request.folder, "removed": n}
