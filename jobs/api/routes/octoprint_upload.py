"""OctoPrint's upload for slicers and CAM post-processors, per machine (seed 002's host).

A client configured for OctoPrint at `http://dncq/machines/1010` asks `GET /api/version`,
then `POST /api/files/local` with the program as the multipart `file`: it lands in the
library as a new version (pending where the machine asks for approval: the
`needs-approval` tag), in the `path` folder, else the folder the file's name gives
(`CAM/PART.gcode`), else the machine's first assigned folder (`uploads` when it has
none), named `filename` when given, and that folder is assigned to the machine. With
`print` or `select` and an approved version, it is sent to the machine as a job.
`userdata` is refused: OctoPrint keeps it with the file, dncq has nowhere to.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, File, Form, Query, Request, UploadFile
from fastapi.responses import JSONResponse
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from jobs import __version__, rollout, service
from jobs.api import library_send
from jobs.api.deps import (
    PrincipalDep,
    SessionDep,
    SettingsDep,
    check_machines,
    key_machine,
    requires,
)
from jobs.api.errors import CodedHTTPError, library_errors, resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Principal, Role
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.fleet.paths import bad
from jobs.job_options import JobOptions
from jobs.library import blobs, names, octoprint_files
from jobs.library import service as library
from jobs.library.models import VersionState
from jobs.models import JobKind
from jobs.settings import Settings

router = APIRouter(tags=["OctoPrint upload"], route_class=CheckedRoute)

OCTOPRINT_API = "0.1"  # the REST API version OctoPrint's clients check
SERVER_AS = "1.11.0"  # the OctoPrint release whose upload this follows
APPROVAL_TAG = "needs-approval"  # a machine whose uploads wait for a programmer
DEFAULT_FOLDER = "uploads"
READ_BYTES = 256 * 1024
# A program of any size, as OctoPrint takes one (1 GB by default): the stream limit's paths.
UPLOAD_PATHS = ("/api/files/local", "/machines/{machine_id}/api/files/local")


# OctoPrint's `valid_boolean_trues`, compared as it compares them: in any case, unstripped.
_TRUES = frozenset({"true", "yes", "y", "1"})


def _truthy(value: str | None) -> bool:
    return (value or "").lower() in _TRUES


@dataclass(frozen=True)
class Asked:
    """The form fields of OctoPrint's upload beside the file."""

    path: str | None  # the folder: a library folder
    filename: str | None  # the name, in place of the file part's own (its folders kept)
    to_select: bool
    to_print: bool
    no_overwrite: bool  # refuse (409) where the program is there already


def _asked(path: Annotated[str | None, Form()] = None,
           filename: Annotated[str | None, Form()] = None,
           select: Annotated[str | None, Form()] = None,
           print_: Annotated[str | None, Form(alias="print")] = None,
           no_overwrite: Annotated[str | None, Form(alias="noOverwrite")] = None,
           userdata: Annotated[str | None, Form()] = None) -> Asked:
    if userdata is not None:  # OctoPrint keeps and lists it: dropped, a client would miss it
        raise CodedHTTPError(400, ErrorCode.BAD_PARAMETER,
                             "userdata: dncq does not keep an upload's userdata, which "
                             "OctoPrint keeps with the file; send the upload without it")
    return Asked(path=path, filename=filename, to_select=_truthy(select),
                 to_print=_truthy(print_), no_overwrite=_truthy(no_overwrite))


AskedDep = Annotated[Asked, Depends(_asked)]


@router.get("/machines/{machine_id}/api/version", summary="OctoPrint's version answer",
            dependencies=[requires(Role.VIEWER)])
def version(session: SessionDep, machine_id: str) -> dict[str, str]:
    with resource_errors():
        registry.get(session=session, machine_id=machine_id)
    return _version()


@router.get("/api/version", summary="OctoPrint's version answer (for clients of one host)",
            dependencies=[requires(Role.VIEWER)])
def version_of_host() -> dict[str, str]:
    return _version()


def _version() -> dict[str, str]:
    return {"api": OCTOPRINT_API, "server": SERVER_AS,
            "text": f"OctoPrint {SERVER_AS} (dncq {__version__})"}


@router.post(UPLOAD_PATHS[0], status_code=201,
             summary="OctoPrint's upload for a client that keeps only the host: the machine "
                     "is named by the key (`KEY@MACHINE`) or `machineID`",
             dependencies=[requires(Role.PROGRAMMER, action="octoprint.upload")])
async def upload_to_host(request: Request, session: SessionDep, settings: SettingsDep,
                         principal: PrincipalDep, file: Annotated[UploadFile, File()],
                         asked: AskedDep,
                         machine_id: Annotated[str | None, Query(alias="machineID")] = None
                         ) -> Any:
    chosen = machine_id or key_machine(request)
    if not chosen:
        raise CodedHTTPError(400, ErrorCode.BAD_PARAMETER,
                             "which machine? upload to /machines/ID/api/files/local, add "
                             "?machineID=ID, or send the key as KEY@ID")
    # The entry's URL keeps `?machineID=` as the listing's do; a key scoped to the machine
    # names it by itself.
    refs = octoprint_files.refs_at(_server(request), "", machine_id)
    return await _upload(session, settings, principal, chosen, refs, file, asked)


@router.post(UPLOAD_PATHS[1], status_code=201,
             summary="Upload a program as OctoPrint takes it: into the library, optionally "
                     "sent to the machine",
             dependencies=[requires(Role.PROGRAMMER, action="octoprint.upload")])
async def upload(request: Request, session: SessionDep, settings: SettingsDep,
                 principal: PrincipalDep, machine_id: str, file: Annotated[UploadFile, File()],
                 asked: AskedDep) -> Any:
    refs = octoprint_files.refs_at(_server(request), f"/machines/{machine_id}")
    return await _upload(session, settings, principal, machine_id, refs, file, asked)


def _server(request: Request) -> str:
    return str(request.base_url).rstrip("/")


async def _upload(session: Session, settings: Settings, principal: Principal, machine_id: str,
                  refs: octoprint_files.Refs, file: UploadFile, asked: Asked) -> JSONResponse:
    """The upload kept, recorded and sent when asked; OctoPrint's 201 answer, whose
    `Location` and `refs.resource` are the file's entry in the machine's `local` listing,
    and `done` whether that entry is the upload (false while it waits for approval)."""
    # An upload assigns its folder to the machine and may send it there: a key limited to
    # some machines uploads for those alone, however it names the machine.
    check_machines(principal, [machine_id])
    # The database work runs beside the event loop, which must not wait on a write lock.
    spec, folder, name = await run_in_threadpool(_where, session, machine_id, asked,
                                                 file.filename or "")
    intake = blobs.Intake(settings)
    try:
        while chunk := await file.read(READ_BYTES):
            intake.add(chunk)
        with library_errors():  # an empty one: before it is kept
            library.check_size(folder=folder, name=name, size_bytes=intake.size)
        blob = intake.keep()
    except BaseException:
        intake.discard()
        raise
    to_select, to_print = asked.to_select, asked.to_print
    added, sent_job = await run_in_threadpool(
        _record, session, settings, spec, folder, name, blob, send=to_select or to_print,
        no_overwrite=asked.no_overwrite)
    # As OctoPrint: `path` is the one the listing gives the file, and `resource` its entry
    # there (listed once approved).
    location = refs.resource("local", f"{folder}/{name}")
    # Not done while the version waits for approval: its entry is 404 until then, as
    # OctoPrint's is while an upload still streams to the printer's SD card (`done` false).
    done = added.version.state is VersionState.APPROVED
    body = {"files": {"local": {"name": name, "display": name, "origin": "local",
                                "path": f"{folder}/{name}",
                                "refs": {"resource": location,
                                         "download": refs.download(folder, name)}}},
            # As OctoPrint answers: each flag as asked, and false when nothing was sent.
            "done": done, "effectiveSelect": to_select and sent_job is not None,
            "effectivePrint": to_print and sent_job is not None,
            "dncq": {"library": f"{folder}/{name}", "version": added.version.number,
                     "state": added.version.state.value, "job": sent_job}}
    return JSONResponse(body, status_code=201, headers={"Location": location})


def _where(session: Any, machine_id: str, asked: Asked,
           filename: str) -> tuple[registry.MachineSpec, str, str]:
    """The machine, the library folder and the name of an upload; 404, 400 or (a program
    there already, with `noOverwrite`) 409 before a byte is kept."""
    with resource_errors():
        spec = registry.get(session=session, machine_id=machine_id)
    steps, _, name = filename.rpartition("/")
    # As OctoPrint: the `path` field names the folder, and the name's own folders are then
    # dropped; without it the name's folders do (`CAM/PART.gcode`), made as OctoPrint makes
    # them. A library folder is the machine's local folder of that path in the listing.
    # The `filename` field names the file in place of the part's own name, not its folder.
    folder = (asked.path or "").strip("/") or steps.strip("/") or _folder_of(session, machine_id)
    with library_errors():
        # A name that climbs out (`../PART.gcode`) is refused, as OctoPrint refuses it.
        if ".." in steps.split("/"):
            raise bad(f"file name {filename!r} climbs out of its folder")
        if asked.filename:
            if "/" in asked.filename or "\\" in asked.filename:  # as OctoPrint refuses it
                raise bad(f"filename {asked.filename!r} names a folder: give the name "
                          "alone, and the folder as path")
            name = asked.filename
        names.check_folder(folder)
        names.check_program_name(name)
    if asked.no_overwrite and library.holds(session=session, folder=folder, name=name):
        raise _overwrite_refused(folder, name)
    return spec, folder, name


def _overwrite_refused(folder: str, name: str) -> CodedHTTPError:
    # As OctoPrint's 409: a new version is what overwriting the file would make.
    return CodedHTTPError(409, ErrorCode.PATH_EXISTS,
                          f"{folder}/{name} is in the library already and noOverwrite was set")


def _record(session: Any, settings: Any, spec: registry.MachineSpec, folder: str, name: str,
            blob: blobs.BlobInfo, *, send: bool,
            no_overwrite: bool) -> tuple[library.Added, str | None]:
    """The upload as a library version, its folder assigned to the machine, and sent when
    asked, approved and small enough for a send job: the version and the send job's id."""
    if no_overwrite:  # asked again, held: another upload may have added it meanwhile
        try:
            library.hold_name(session=session, folder=folder, name=name)
        except ContractError:
            raise _overwrite_refused(folder, name) from None
    with library_errors():
        added = library.add(session=session, folder=folder, name=name, blob=blob,
                            note="uploaded as to OctoPrint", created_by="octoprint-upload",
                            source=f"upload for machine {spec.id}",
                            approve=APPROVAL_TAG not in spec.tags)
        library.assign(session=session, folder=folder, machine_ids=[spec.id])
    if not send or added.version.state is not VersionState.APPROVED:
        return added, None
    if added.version.size > library_send.SEND_MAX_BYTES:  # kept, as a send job refuses it
        return added, None
    session.commit()  # the version exists for the job's own transactions
    return added, _send(session, settings, spec.id, added)


def _folder_of(session: Any, machine_id: str) -> str:
    """Where an upload without `path` goes: the machine's first assigned folder."""
    assigned = library.assignments(session=session, machine_id=machine_id)
    return assigned[0].folder if assigned else DEFAULT_FOLDER


def _send(session: Any, settings: Any, machine_id: str, added: library.Added) -> str:
    """A send job of the uploaded version to the machine, recording the version; its id."""
    data = library_send.content(settings=settings, sent=added.version)
    payload = service.store_payload(session=session, data=data)
    targets = [service.TargetIn(machineID=machine_id, fileName=added.version.program.name)]
    job = rollout.submit(session=session, settings=settings, kind=JobKind.SEND,
                         targets=targets, options=JobOptions(replace=True),
                         payload_id=payload, created_by="octoprint-upload",
                         recorded=library_send.recorder(added.version))
    return job.id
