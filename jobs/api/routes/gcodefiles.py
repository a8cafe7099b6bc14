"""OctoPrint's file listing for each machine: `local` is dncq's store for it, `sdcard`
the machine's own storage; in the seed's shape (seed 002, `gcodefiles`) and in today's
OctoPrint's (`GET /api/files`, what its clients ask for).

Served under `/machines/{machineID}/api/...`, so a client written for OctoPrint pointed at
`http://dncq/machines/1010` with the API key lists that machine; and under `/api/...` with
`?machineID=` for clients that take one URL.
"""

from __future__ import annotations

import shutil
import string
from dataclasses import dataclass
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from jobs.api.deps import SessionDep, SettingsDep, key_machine, requires
from jobs.api.errors import CodedHTTPError, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.errors import ContractError, ErrorCode, resource_status
from jobs.fleet import registry
from jobs.library import octoprint_files, record, seed_listing
from jobs.run.slot import machine_slot

router = APIRouter(tags=["OctoPrint listing"], route_class=CheckedRoute)

MachineInPath = Annotated[str, Path(description="The machine, as machineID", max_length=64)]
MachineInQuery = Annotated[str | None, Query(
    alias="machineID", max_length=64,
    description="The machine (or send the key scoped to it: KEY@MACHINE)")]


UNREACHABLE_HEADER = "X-Dncq-Sdcard-Unreachable"
# A header says printable ASCII as it is; anything else (a name in the machine's own
# language, a control character) is percent-encoded, and so is `%` itself.
_SAID_AS_IS = " " + string.punctuation.replace("%", "")


@dataclass
class _Gathered:
    files: list[seed_listing.ListedFile]
    machine_free: int | None = None  # None: its transport does not tell, or not asked
    unreachable: ContractError | None = None  # why the machine's own files are left out


def _gathered(session: Any, settings: Any, machine_id: str, origin: str | None) -> _Gathered:
    """The machine's files of `origin` (both when None), and the machine's free bytes.

    Both asked of a machine that cannot be reached now (offline, busy, not answering):
    the local files alone, as OctoPrint lists them while its printer is not connected, and
    the reason kept for the answer's header. Asked for `sdcard` alone, its refusal (409).
    """
    with resource_errors():
        spec = registry.get(session=session, machine_id=machine_id)
    gathered = _Gathered(files=[])
    if origin in (None, "local"):
        gathered.files += seed_listing.local_files(session=session, settings=settings,
                                                   spec=spec)
    if origin in (None, "sdcard"):
        session.commit()  # no read transaction open during the machine's work
        # One of the machine's slots, as every other reader takes: a listener on its
        # link gives way, and the machine sees no more operations than it allows (none
        # where the listing is dncq's copies of an RS-232 line's programs).
        try:
            with machine_slot(settings, spec, reading=True):
                on_machine, gathered.machine_free = seed_listing.sdcard_files(
                    spec, data_dir=settings.data_dir)
        except ContractError as exc:
            if origin is not None or not exc.transient:
                raise CodedHTTPError(resource_status(exc), exc.code, exc.status_msg) from None
            gathered.unreachable = exc
        else:
            gathered.files += on_machine
    return gathered


def _said(gathered: _Gathered, answer: dict[str, Any]) -> JSONResponse:
    """The listing, with why the machine's own files are not in it where they are not."""
    headers = {}
    if gathered.unreachable is not None:
        headers[UNREACHABLE_HEADER] = quote(str(gathered.unreachable), safe=_SAID_AS_IS)
    return JSONResponse(answer, headers=headers)


def _answer(session: Any, settings: Any, machine_id: str, origin: str | None) -> JSONResponse:
    if origin is not None and origin not in seed_listing.ORIGINS:
        raise CodedHTTPError(400, ErrorCode.BAD_PARAMETER,
                             f"origin is local or sdcard, not {origin!r}")
    gathered = _gathered(session, settings, machine_id, origin)
    prints = seed_listing.prints_by_program(session=session, machine_id=machine_id)
    # `free` is the local store's, as in OctoPrint; the machine's own when only it is asked.
    free = seed_listing.told_size(gathered.machine_free) if origin == "sdcard" \
        else seed_listing.local_free(settings.data_dir)
    return _said(gathered, seed_listing.listing(gathered.files, prints, free))


def _listed(session: Any, settings: Any, machine_id: str, origin: str | None,
            refs: octoprint_files.Refs) -> tuple[_Gathered, dict[str, Any]]:
    """Today's OctoPrint listing (`GET /api/files`): another origin is 404, as there."""
    if origin is not None and origin not in seed_listing.ORIGINS:
        raise CodedHTTPError(404, ErrorCode.PATH_NOT_FOUND, f"no origin {origin!r}")
    gathered = _gathered(session, settings, machine_id, origin)
    runs = record.runs_by_program(session=session, machine_id=machine_id)
    free = total = None
    if origin != "sdcard":  # OctoPrint tells its upload folder's space beside `local`
        usage = shutil.disk_usage(settings.data_dir)
        free, total = usage.free, usage.total
    return gathered, octoprint_files.listing(gathered.files, runs, refs, free=free, total=total)


def _files(session: Any, settings: Any, machine_id: str, origin: str | None,
           refs: octoprint_files.Refs) -> JSONResponse:
    return _said(*_listed(session, settings, machine_id, origin, refs))


def _file(session: Any, settings: Any, machine_id: str, origin: str, path: str,
          refs: octoprint_files.Refs) -> dict[str, Any]:
    """One file's entry of today's listing; 404 when there is none of that path."""
    listed = _listed(session, settings, machine_id, origin, refs)[1]["files"]
    found = next((f for f in listed if f["path"] == path), None)
    if found is None:
        raise CodedHTTPError(404, ErrorCode.PATH_NOT_FOUND, f"no file {path!r} in {origin}")
    return found


def _refs(request: Request, prefix: str, machine_id: str | None = None
          ) -> octoprint_files.Refs:
    """The listing's URLs under `prefix`."""
    return octoprint_files.refs_at(str(request.base_url).rstrip("/"), prefix, machine_id)


@router.get("/machines/{machine_id}/api/gcodefiles",
            summary="Every file of the machine from both origins (OctoPrint's listing)",
            dependencies=[requires(Role.VIEWER)])
async def all_files(session: SessionDep, settings: SettingsDep,
                    machine_id: MachineInPath) -> JSONResponse:
    return await run_in_threadpool(_answer, session, settings, machine_id, None)


@router.get("/machines/{machine_id}/api/gcodefiles/{origin}",
            summary="The machine's files from one origin: local or sdcard",
            dependencies=[requires(Role.VIEWER)])
async def origin_files(session: SessionDep, settings: SettingsDep, machine_id: MachineInPath,
                       origin: str) -> JSONResponse:
    return await run_in_threadpool(_answer, session, settings, machine_id, origin)


def _chosen(request: Request, machine_id: str | None) -> str:
    chosen = machine_id or key_machine(request)
    if not chosen:
        raise CodedHTTPError(400, ErrorCode.BAD_PARAMETER,
                             "which machine? add ?machineID=ID or send the key as KEY@ID")
    return chosen


@router.get("/api/gcodefiles", summary="OctoPrint's listing of the machine given as machineID",
            dependencies=[requires(Role.VIEWER)])
async def all_files_of(request: Request, session: SessionDep, settings: SettingsDep,
                       machine_id: MachineInQuery = None) -> JSONResponse:
    return await run_in_threadpool(_answer, session, settings, _chosen(request, machine_id),
                                   None)


@router.get("/api/gcodefiles/{origin}",
            summary="One origin of OctoPrint's listing of the machine given as machineID",
            dependencies=[requires(Role.VIEWER)])
async def origin_files_of(request: Request, session: SessionDep, settings: SettingsDep,
                          origin: str, machine_id: MachineInQuery = None) -> JSONResponse:
    return await run_in_threadpool(_answer, session, settings, _chosen(request, machine_id),
                                   origin)


# -- today's OctoPrint listing ----------------------------------------------------------


@router.get("/machines/{machine_id}/api/files",
            summary="Every file of the machine, as today's OctoPrint lists files",
            dependencies=[requires(Role.VIEWER)])
async def files_now(request: Request, session: SessionDep, settings: SettingsDep,
                    machine_id: MachineInPath) -> JSONResponse:
    return await run_in_threadpool(_files, session, settings, machine_id, None,
                                   _refs(request, f"/machines/{machine_id}"))


@router.get("/machines/{machine_id}/api/files/{origin}",
            summary="The machine's files from one origin, as today's OctoPrint lists them",
            dependencies=[requires(Role.VIEWER)])
async def origin_files_now(request: Request, session: SessionDep, settings: SettingsDep,
                           machine_id: MachineInPath, origin: str) -> JSONResponse:
    return await run_in_threadpool(_files, session, settings, machine_id, origin,
                                   _refs(request, f"/machines/{machine_id}"))


@router.get("/machines/{machine_id}/api/files/{origin}/{path:path}",
            summary="One file's information, as today's OctoPrint gives it",
            dependencies=[requires(Role.VIEWER)])
async def file_now(request: Request, session: SessionDep, settings: SettingsDep,
                   machine_id: MachineInPath, origin: str, path: str) -> dict[str, Any]:
    return await run_in_threadpool(_file, session, settings, machine_id, origin, path,
                                   _refs(request, f"/machines/{machine_id}"))


@router.get("/api/files", summary="Today's OctoPrint listing of the machine given as machineID",
            dependencies=[requires(Role.VIEWER)])
async def files_now_of(request: Request, session: SessionDep, settings: SettingsDep,
                       machine_id: MachineInQuery = None) -> JSONResponse:
    return await run_in_threadpool(_files, session, settings, _chosen(request, machine_id),
                                   None, _refs(request, "", machine_id))


@router.get("/api/files/{origin}",
            summary="One origin of today's OctoPrint listing of the machine given as machineID",
            dependencies=[requires(Role.VIEWER)])
async def origin_files_now_of(request: Request, session: SessionDep, settings: SettingsDep,
                              origin: str, machine_id: MachineInQuery = None) -> JSONResponse:
    return await run_in_threadpool(_files, session, settings, _chosen(request, machine_id),
                                   origin, _refs(request, "", machine_id))


@router.get("/api/files/{origin}/{path:path}",
            summary="One file's information, of the machine given as machineID",
            dependencies=[requires(Role.VIEWER)])
async def file_now_of(request: Request, session: SessionDep, settings: SettingsDep,
                      origin: str, path: str, machine_id: MachineInQuery = None
                      ) -> dict[str, Any]:
    return await run_in_threadpool(_file, session, settings, _chosen(request, machine_id),
                                   origin, path, _refs(request, "", machine_id))
