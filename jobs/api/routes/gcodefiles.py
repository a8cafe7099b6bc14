"""OctoPrint's file listing (seed 002) for each machine: `local` is dncq's store for it,
`sdcard` the machine's own storage.

Served under `/machines/{machineID}/api/...`, so a client written for OctoPrint pointed at
`http://dncq/machines/1010` with the API key lists that machine; and under `/api/...` with
`?machineID=` for clients that take one URL.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request
from starlette.concurrency import run_in_threadpool

from jobs.api.deps import SessionDep, SettingsDep, key_machine, requires
from jobs.api.errors import CodedHTTPError, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.errors import ErrorCode
from jobs.fleet import registry
from jobs.library import seed_listing
from jobs.run.slot import machine_slot

router = APIRouter(tags=["OctoPrint listing"], route_class=CheckedRoute)

MachineInPath = Annotated[str, Path(description="The machine, as machineID", max_length=64)]
MachineInQuery = Annotated[str | None, Query(
    alias="machineID", max_length=64,
    description="The machine (or send the key scoped to it: KEY@MACHINE)")]


def _answer(session: Any, settings: Any, machine_id: str, origin: str | None) -> dict[str, Any]:
    if origin is not None and origin not in seed_listing.ORIGINS:
        raise CodedHTTPError(400, ErrorCode.BAD_PARAMETER,
                             f"origin is local or sdcard, not {origin!r}")
    with resource_errors():
        spec = registry.get(session=session, machine_id=machine_id)
    prints = seed_listing.prints_by_program(session=session, machine_id=machine_id)
    files: list[seed_listing.ListedFile] = []
    # `free` is the local store's, as in OctoPrint; the machine's own when only it is asked.
    free = seed_listing.local_free(settings.data_dir)
    if origin in (None, "local"):
        files += seed_listing.local_files(session=session, settings=settings, spec=spec)
    if origin in (None, "sdcard"):
        session.commit()  # no read transaction open during the machine's work
        # One of the machine's slots, as every other reader takes: a listener on its
        # link gives way, and the machine sees no more operations than it allows.
        with resource_errors(), machine_slot(settings, spec):
            on_machine, machine_free = seed_listing.sdcard_files(spec, data_dir=settings.data_dir)
        files += on_machine
        if origin == "sdcard":
            free = machine_free
    return seed_listing.listing(files, prints, free)


@router.get("/machines/{machine_id}/api/gcodefiles",
            summary="Every file of the machine from both origins (OctoPrint's listing)",
            dependencies=[requires(Role.VIEWER)])
async def all_files(session: SessionDep, settings: SettingsDep,
                    machine_id: MachineInPath) -> dict[str, Any]:
    return await run_in_threadpool(_answer, session, settings, machine_id, None)


@router.get("/machines/{machine_id}/api/gcodefiles/{origin}",
            summary="The machine's files from one origin: local or sdcard",
            dependencies=[requires(Role.VIEWER)])
async def origin_files(session: SessionDep, settings: SettingsDep, machine_id: MachineInPath,
                       origin: str) -> dict[str, Any]:
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
                       machine_id: MachineInQuery = None) -> dict[str, Any]:
    return await run_in_threadpool(_answer, session, settings, _chosen(request, machine_id),
                                   None)


@router.get("/api/gcodefiles/{origin}",
            summary="One origin of OctoPrint's listing of the machine given as machineID",
            dependencies=[requires(Role.VIEWER)])
async def origin_files_of(request: Request, session: SessionDep, settings: SettingsDep,
                          origin: str, machine_id: MachineInQuery = None) -> dict[str, Any]:
    return await run_in_threadpool(_answer, session, settings, _chosen(request, machine_id),
                                   origin)
